//! Errors told in words: a cause chain in one line, a full disk told
//! from its operating-system code.

use std::io;

/// An error and its sources as one line, `: `-separated, a cause the text
/// already ends with written once.
pub fn error_chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let cause_text = cause.to_string();
        if !text.ends_with(&cause_text) {
            text.push_str(": ");
            text.push_str(&cause_text);
        }
        source = cause.source();
    }
    text
}

/// The operating system's "no space left on device" (ENOSPC: 28 on Linux
/// and the BSDs) and "disk quota exceeded" (EDQUOT) codes;
/// `io::ErrorKind::StorageFull` would say it by kind, but needs a newer
/// Rust than this crate's minimum.
#[cfg(target_os = "linux")]
const STORAGE_FULL_CODES: &[i32] = &[28, 122];
#[cfg(all(unix, not(target_os = "linux")))]
const STORAGE_FULL_CODES: &[i32] = &[28, 69];
/// Windows' ERROR_HANDLE_DISK_FULL and ERROR_DISK_FULL.
#[cfg(windows)]
const STORAGE_FULL_CODES: &[i32] = &[39, 112];
#[cfg(not(any(unix, windows)))]
const STORAGE_FULL_CODES: &[i32] = &[];

/// Whether an I/O error means that the disk is full (or the quota used
/// up): what an upload or the database answers with a 507.
pub fn is_storage_full(error: &io::Error) -> bool {
    error
        .raw_os_error()
        .is_some_and(|code| STORAGE_FULL_CODES.contains(&code))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_disk_is_told_from_other_io_errors() {
        assert!(is_storage_full(&io::Error::from_raw_os_error(28)));
        assert!(!is_storage_full(&io::Error::from_raw_os_error(13)));
        assert!(!is_storage_full(&io::Error::other("no space")));
    }
}
