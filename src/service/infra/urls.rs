//! The URLs of the service's two stores, as the flags give them:
//! `--database` ([`PostgresUrl`]) and `--object-store` ([`ObjectStoreUrl`]).

use std::fmt;
use std::str::FromStr;

/// A PostgreSQL connection URL (`postgres://` or `postgresql://`), as
/// `--database` / `PTV_DATABASE_URL` give it. Shown without its password.
#[derive(Clone, PartialEq, Eq)]
pub struct PostgresUrl(String);

impl PostgresUrl {
    /// The URL, password included, for connecting.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// The server it names, `HOST:PORT` (as libpq reads the URL: a host
    /// or port left out is the environment's or the default), for
    /// messages; `None` if the URL does not parse.
    pub fn server(&self) -> Option<String> {
        let options = sqlx::postgres::PgConnectOptions::from_str(&self.0).ok()?;
        Some(format!("{}:{}", options.get_host(), options.get_port()))
    }
}

impl FromStr for PostgresUrl {
    type Err = String;

    fn from_str(url: &str) -> Result<Self, Self::Err> {
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Ok(PostgresUrl(url.to_owned()))
        } else {
            Err(format!(
                "`{}` is not a PostgreSQL URL (postgres://USER@HOST:PORT/DATABASE); \
                 leave --database out for SQLite in the data directory",
                redacted(url)
            ))
        }
    }
}

impl fmt::Debug for PostgresUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "PostgresUrl({})", redacted(&self.0))
    }
}

impl fmt::Display for PostgresUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&redacted(&self.0))
    }
}

/// A URL with the password of its user part replaced by `***`.
fn redacted(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_owned();
    };
    let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    match authority.rsplit_once('@') {
        Some((user, host)) => match user.split_once(':') {
            Some((name, _)) => format!("{scheme}://{name}:***@{host}{path}"),
            None => url.to_owned(),
        },
        None => url.to_owned(),
    }
}

/// Where images are stored: `--object-store`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ObjectStoreUrl {
    /// The bucket.
    pub bucket: String,
    /// The prefix within it, without slashes at either end (may be empty).
    pub prefix: String,
}

impl std::str::FromStr for ObjectStoreUrl {
    type Err = String;

    /// `s3://bucket` or `s3://bucket/prefix/of/any/depth`.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let rest = text.strip_prefix("s3://").ok_or_else(|| {
            format!(
                "`{text}` is not an s3:// URL; give s3://bucket/prefix (leave the option out \
                 for images in the data directory)"
            )
        })?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let valid_bucket = (3..=63).contains(&bucket.len())
            && bucket
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'.');
        if !valid_bucket {
            return Err(format!(
                "`{bucket}` is not an S3 bucket name (3 to 63 lower-case letters, digits, \
                 dots and hyphens): give s3://bucket/prefix"
            ));
        }
        let prefix = prefix.trim_matches('/');
        if prefix.split('/').any(|p| p == "." || p == "..")
            || prefix.contains("//")
            || prefix.chars().any(char::is_control)
        {
            return Err(format!(
                "`{prefix}` is not a usable prefix: no empty, `.` or `..` parts"
            ));
        }
        Ok(ObjectStoreUrl {
            bucket: bucket.to_owned(),
            prefix: prefix.to_owned(),
        })
    }
}

impl std::fmt::Display for ObjectStoreUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "s3://{}/{}", self.bucket, self.prefix)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_postgres_url_is_taken_and_shown_without_its_password() {
        let url: PostgresUrl = "postgres://ptv:secret@db.lab:5432/ptv".parse().unwrap();
        assert_eq!(url.as_str(), "postgres://ptv:secret@db.lab:5432/ptv");
        assert_eq!(url.to_string(), "postgres://ptv:***@db.lab:5432/ptv");
        assert!(!format!("{url:?}").contains("secret"));
        let error = "mysql://ptv:secret@db/ptv"
            .parse::<PostgresUrl>()
            .unwrap_err();
        assert!(error.contains("not a PostgreSQL URL"), "{error}");
        assert!(!error.contains("secret"), "{error}");
    }

    #[test]
    fn object_store_urls_are_parsed_or_refused_saying_why() {
        let url: ObjectStoreUrl = "s3://ptv-images/lab/campaign-7/".parse().unwrap();
        assert_eq!(url.bucket, "ptv-images");
        assert_eq!(url.prefix, "lab/campaign-7");
        let bare: ObjectStoreUrl = "s3://ptv-images".parse().unwrap();
        assert_eq!(bare.prefix, "");
        for (bad, says) in [
            ("/data/images", "not an s3:// URL"),
            ("gs://bucket/x", "not an s3:// URL"),
            ("s3://", "not an S3 bucket name"),
            ("s3://Upper/x", "not an S3 bucket name"),
            ("s3://ab/x", "not an S3 bucket name"),
            ("s3://bucket/a/../b", "not a usable prefix"),
            ("s3://bucket/a//b", "not a usable prefix"),
        ] {
            let error = bad.parse::<ObjectStoreUrl>().unwrap_err();
            assert!(error.contains(says), "{bad}: {error}");
        }
    }
}
