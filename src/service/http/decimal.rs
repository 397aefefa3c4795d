//! The one parser of the integers the HTTP layer takes from text: frame
//! numbers and sizes in multipart text parts, the camera index in part
//! names (`cam0`, `targets2`, ...), path segments and query values
//! ([`super::problem::ApiPath`], [`super::problem::ApiQuery`] check every
//! integer-looking one), `Last-Event-ID`.
//!
//! One form only: ASCII decimal digits, no sign, no spaces, no leading
//! zeros (`0` itself aside). Rust's own `parse` also takes `+5`, and
//! trimming took ` 5` and `5\n`; `05` and `cam00` read as 5 and `cam0`.
//! Each of those is a client's mistake or a probe, never a second
//! spelling of a number: one spelling per number keeps a frame from
//! being uploaded twice under two names, and what the server stores is
//! what the client wrote.

use std::str::FromStr;

/// The accepted form, for messages.
pub const FORM: &str =
    "decimal digits only, without sign, spaces or leading zeros (e.g. `5`, `0`, `10001`)";

/// Why a text is not a number.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refused {
    /// Not in the accepted form ([`FORM`]).
    Form,
    /// In the form, but beyond the type's range.
    Range,
}

/// `text` as a `T`, if it is in the accepted form ([`FORM`]) and within
/// `T`'s range.
pub fn parse<T: FromStr>(text: &str) -> Result<T, Refused> {
    let canonical = !text.is_empty()
        && text.bytes().all(|b| b.is_ascii_digit())
        && (text == "0" || !text.starts_with('0'));
    if !canonical {
        return Err(Refused::Form);
    }
    text.parse().map_err(|_| Refused::Range)
}

/// Whether `text` is meant as an integer: digits, perhaps with a sign,
/// spaces or leading zeros. Such a path segment or query value must be in
/// the accepted form; other text (a file name, a range `1..5`, a word) is
/// for its own parser.
pub fn looks_like_integer(text: &str) -> bool {
    text.bytes().any(|b| b.is_ascii_digit())
        && text
            .bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'+' | b'-' | b' ' | b'\t' | b'\r' | b'\n'))
}

/// Checks the integer-looking values among `pairs` (name, value): the
/// first one not in the accepted form, as a message naming it (`what` is
/// "path segment", "query parameter").
pub fn check_pairs<'a>(
    what: &str,
    pairs: impl IntoIterator<Item = (&'a str, &'a str)>,
) -> Result<(), String> {
    for (name, value) in pairs {
        if looks_like_integer(value) && parse::<u64>(value) == Err(Refused::Form) {
            return Err(format!(
                "{what} `{}` is `{}`; give an integer as {FORM}",
                name.escape_debug(),
                value.escape_debug()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_spelling_per_number() {
        assert_eq!(parse::<u32>("5"), Ok(5));
        assert_eq!(parse::<u32>("0"), Ok(0));
        assert_eq!(parse::<u32>("10001"), Ok(10001));
        assert_eq!(parse::<u32>("4294967295"), Ok(u32::MAX));
        for text in [
            " 5", "+5", "05", "5\n", "5 ", "-5", "-0", "00", "", "5x", "0x5", "5.0", "1e3", "٥",
        ] {
            assert_eq!(parse::<u32>(text), Err(Refused::Form), "{text:?}");
        }
        assert_eq!(parse::<u32>("4294967296"), Err(Refused::Range));
        assert_eq!(parse::<u64>("99999999999999999999"), Err(Refused::Range));
    }

    #[test]
    fn integer_looking_values_are_checked_and_others_left_alone() {
        for text in [" 5", "+5", "05", "5\n", "-1", "007"] {
            assert!(looks_like_integer(text), "{text:?}");
            assert!(check_pairs("path segment", [("frame", text)]).is_err());
        }
        for text in ["5", "0", "0.ori", "1..5", "csv", "", "+", " "] {
            assert!(
                check_pairs("path segment", [("x", text)]).is_ok(),
                "{text:?}"
            );
        }
        // Out of u64's range is left to the type's parser (it refuses it
        // with its own message).
        assert!(check_pairs("query parameter", [("run", "99999999999999999999")]).is_ok());
        let message = check_pairs("path segment", [("frame", "+5")]).unwrap_err();
        assert!(
            message.contains("path segment `frame` is `+5`"),
            "{message}"
        );
        assert!(
            message.contains("without sign, spaces or leading zeros"),
            "{message}"
        );
    }
}
