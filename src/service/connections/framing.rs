//! Which request heads on a connection declare both `Content-Length` and
//! `Transfer-Encoding`, read from the bytes as they arrive.
//!
//! Hyper frames such a request by its transfer coding, drops the
//! `Content-Length` before the service sees the request, and closes the
//! connection after answering (RFC 9112 section 6.1), so the service
//! cannot tell it from a plain chunked request. RFC 9112 allows a server
//! to refuse it instead, which is what the service does (a 400): a front
//! proxy that framed it by its length would disagree with this service on
//! where the request ends (request smuggling). So the connection's bytes
//! pass through a [`Framing`] before hyper reads them, which follows the
//! HTTP/1.1 framing (heads, bodies by length or chunked) and notes for
//! each head, in order, whether it declares both. The service's handler
//! takes one note per request (hyper parses the same heads in the same
//! order, and the scan of a read completes before hyper sees its bytes).
//!
//! Anything it does not follow (a head or chunk line too long, a length
//! that does not parse, a `CONNECT`) stops the scan for the rest of the
//! connection, and later requests then get no note: the service refuses
//! them (fails closed, see [`super::RefusedFraming`]). A head with an
//! `Upgrade` field is followed like any other: the service never answers
//! 101 Switching Protocols, so hyper reads the bytes after it as HTTP.

use std::collections::VecDeque;

/// The longest line the scan holds: hyper's whole head may not be longer.
const MAX_LINE: usize = super::HYPER_MAX_HEAD_BYTES;
/// The longest chunk-size line (with extensions) the scan follows.
const MAX_CHUNK_LINE: usize = 4096;

/// Where in the framing the scan is.
#[derive(Debug)]
enum State {
    /// In a request head: before its request line, or in its fields.
    Head {
        /// The request line has been seen.
        started: bool,
        /// A `Content-Length` field has been seen.
        length: Option<u64>,
        /// A `Content-Length` field has been seen, parsed or not.
        has_length: bool,
        /// A `Transfer-Encoding` field has been seen.
        coded: bool,
        /// Its last coding is `chunked`.
        chunked: bool,
        /// A `CONNECT`: the bytes after the head are not followed.
        connect: bool,
    },
    /// In a body of known length: bytes still to come.
    Fixed(u64),
    /// In a chunk-size line.
    ChunkSize,
    /// In a chunk's data: bytes still to come, then its CRLF.
    ChunkData(u64),
    /// In the CRLF after a chunk's data.
    ChunkEnd,
    /// In the trailer fields after the last chunk.
    Trailers,
    /// Not following any more.
    Lost,
}

impl State {
    fn head() -> State {
        State::Head {
            started: false,
            length: None,
            has_length: false,
            coded: false,
            chunked: false,
            connect: false,
        }
    }
}

/// The scan of one connection's incoming bytes.
#[derive(Debug)]
pub struct Framing {
    state: State,
    /// The current line (head field, chunk-size line, trailer), without
    /// its line feed.
    line: Vec<u8>,
    /// For each head completed and not yet taken: whether it declared
    /// both a length and a transfer coding.
    notes: VecDeque<bool>,
}

impl Default for Framing {
    fn default() -> Self {
        Framing {
            state: State::head(),
            line: Vec::new(),
            notes: VecDeque::new(),
        }
    }
}

impl Framing {
    /// The next head's note, in order: `Some(true)` if it declared both
    /// `Content-Length` and `Transfer-Encoding`; `None` if no head is
    /// known (the scan stopped following).
    pub fn take_note(&mut self) -> Option<bool> {
        self.notes.pop_front()
    }

    /// Follows `bytes`, the next ones the connection received.
    pub fn scan(&mut self, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            match &mut self.state {
                State::Lost => return,
                State::Fixed(remaining) => {
                    let take = (*remaining).min(bytes.len() as u64);
                    *remaining -= take;
                    bytes = &bytes[take as usize..];
                    if *remaining == 0 {
                        self.state = State::head();
                    }
                }
                State::ChunkData(remaining) => {
                    let take = (*remaining).min(bytes.len() as u64);
                    *remaining -= take;
                    bytes = &bytes[take as usize..];
                    if *remaining == 0 {
                        self.state = State::ChunkEnd;
                    }
                }
                State::Head { .. } | State::ChunkSize | State::ChunkEnd | State::Trailers => {
                    let limit = match self.state {
                        State::ChunkSize => MAX_CHUNK_LINE,
                        _ => MAX_LINE,
                    };
                    match bytes.iter().position(|&b| b == b'\n') {
                        Some(end) => {
                            self.line.extend_from_slice(&bytes[..end]);
                            bytes = &bytes[end + 1..];
                            if self.line.len() > limit {
                                self.state = State::Lost;
                                return;
                            }
                            let mut line = std::mem::take(&mut self.line);
                            if line.last() == Some(&b'\r') {
                                line.pop();
                            }
                            self.line_ended(&line);
                            line.clear();
                            self.line = line;
                        }
                        None => {
                            self.line.extend_from_slice(bytes);
                            if self.line.len() > limit {
                                self.state = State::Lost;
                            }
                            return;
                        }
                    }
                }
            }
        }
    }

    /// A whole line (without CR LF) in a head, a chunk-size line, the CRLF
    /// after a chunk or a trailer.
    fn line_ended(&mut self, line: &[u8]) {
        match &mut self.state {
            State::Head {
                started,
                length,
                has_length,
                coded,
                chunked,
                connect,
            } => {
                if !*started {
                    // Empty lines before a request line are skipped (RFC
                    // 9112 section 2.2), as hyper does.
                    if !line.is_empty() {
                        *started = true;
                        *connect = line.starts_with(b"CONNECT ");
                    }
                    return;
                }
                if line.is_empty() {
                    let both = *has_length && *coded;
                    let next = if *connect {
                        State::Lost
                    } else if *coded {
                        if *chunked {
                            State::ChunkSize
                        } else {
                            // Hyper refuses a coding other than chunked.
                            State::Lost
                        }
                    } else if *has_length {
                        match *length {
                            Some(0) => State::head(),
                            Some(n) => State::Fixed(n),
                            None => State::Lost,
                        }
                    } else {
                        State::head()
                    };
                    self.notes.push_back(both);
                    self.state = next;
                    return;
                }
                let Some(colon) = line.iter().position(|&b| b == b':') else {
                    return;
                };
                let name = &line[..colon];
                let value = trim(&line[colon + 1..]);
                if name.eq_ignore_ascii_case(b"content-length") {
                    let parsed = std::str::from_utf8(value)
                        .ok()
                        .filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()))
                        .and_then(|v| v.parse::<u64>().ok());
                    *length = match (*has_length, *length, parsed) {
                        (false, _, parsed) => parsed,
                        (true, Some(a), Some(b)) if a == b => Some(a),
                        _ => None,
                    };
                    *has_length = true;
                } else if name.eq_ignore_ascii_case(b"transfer-encoding") {
                    *coded = true;
                    let last = value.rsplit(|&b| b == b',').next().map(trim);
                    *chunked = last.is_some_and(|c| c.eq_ignore_ascii_case(b"chunked"));
                }
            }
            State::ChunkSize => {
                let size = line.split(|&b| b == b';').next().map_or(&[][..], trim);
                let parsed = std::str::from_utf8(size)
                    .ok()
                    .filter(|s| !s.is_empty() && s.len() <= 16)
                    .and_then(|s| u64::from_str_radix(s, 16).ok());
                self.state = match parsed {
                    Some(0) => State::Trailers,
                    Some(n) => State::ChunkData(n),
                    None => State::Lost,
                };
            }
            State::ChunkEnd => {
                self.state = if line.is_empty() {
                    State::ChunkSize
                } else {
                    State::Lost
                };
            }
            State::Trailers => {
                if line.is_empty() {
                    self.state = State::head();
                }
            }
            State::Fixed(_) | State::ChunkData(_) | State::Lost => {}
        }
    }
}

/// `bytes` without spaces and tabs around it.
fn trim(bytes: &[u8]) -> &[u8] {
    let start = bytes
        .iter()
        .position(|b| !matches!(b, b' ' | b'\t'))
        .unwrap_or(bytes.len());
    let end = bytes
        .iter()
        .rposition(|b| !matches!(b, b' ' | b'\t'))
        .map_or(start, |e| e + 1);
    &bytes[start..end.max(start)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The notes of `wire` fed in pieces of `piece` bytes.
    fn notes(wire: &[u8], piece: usize) -> Vec<bool> {
        let mut framing = Framing::default();
        for part in wire.chunks(piece) {
            framing.scan(part);
        }
        std::iter::from_fn(|| framing.take_note()).collect()
    }

    #[test]
    fn heads_bodies_and_chunks_are_followed_in_any_pieces() {
        let wire: &[u8] = b"\r\nGET / HTTP/1.1\r\nHost: x\r\n\r\n\
            POST /a HTTP/1.1\r\nContent-Length: 30\r\n\r\n\
            Transfer-Encoding: chunked\r\n\r\n\
            POST /b HTTP/1.1\r\ntransfer-encoding: gzip, Chunked\r\n\r\n\
            5;ext=1\r\nhello\r\n1a\r\nContent-Length: 5\r\n\r\nabcde\r\n0\r\nX-Trailer: 1\r\n\r\n\
            POST /c HTTP/1.1\r\nContent-Length: 4\r\nTransfer-Encoding: chunked\r\n\r\n\
            0\r\n\r\n\
            POST /d HTTP/1.1\nTRANSFER-ENCODING: chunked\nContent-Length: 4\n\n0\n\n\
            GET /e HTTP/1.1\r\n\r\n";
        for piece in [1, 2, 3, 7, 64, wire.len()] {
            assert_eq!(
                notes(wire, piece),
                [false, false, false, true, true, false],
                "in pieces of {piece}"
            );
        }
    }

    #[test]
    fn what_it_cannot_follow_stops_the_notes() {
        // A length that does not parse: hyper refuses it and closes.
        assert_eq!(
            notes(
                b"POST / HTTP/1.1\r\nContent-Length: x\r\n\r\nGET / HTTP/1.1\r\n\r\n",
                5
            ),
            [false]
        );
        // A bad chunk size.
        assert_eq!(
            notes(
                b"POST / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n",
                5
            ),
            [false]
        );
        // A line past the limit.
        let mut long = b"GET / HTTP/1.1\r\nX: ".to_vec();
        long.resize(MAX_LINE + 100, b'a');
        assert!(notes(&long, 1000).is_empty());
        // Two lengths that differ: hyper refuses it.
        assert_eq!(
            notes(
                b"POST / HTTP/1.1\r\nContent-Length: 1\r\nContent-Length: 2\r\n\r\nxGET / HTTP/1.1\r\n\r\n",
                3
            ),
            [false]
        );
    }

    #[test]
    fn upgrades_are_followed_and_connect_stops_the_notes() {
        // The service never answers 101, so what follows an upgrade is
        // the next request, and it is noted.
        let wire: &[u8] = b"GET / HTTP/1.1\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\r\n\
            POST / HTTP/1.1\r\nContent-Length: 4\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n";
        for piece in [1, 5, wire.len()] {
            assert_eq!(notes(wire, piece), [false, true], "in pieces of {piece}");
        }
        // A CONNECT (refused, and its connection closed) is noted, and
        // nothing after it: a request there would be refused.
        assert_eq!(
            notes(b"CONNECT x:443 HTTP/1.1\r\n\r\nGET / HTTP/1.1\r\n\r\n", 4),
            [false]
        );
    }

    #[test]
    fn trim_strips_spaces_and_tabs() {
        assert_eq!(trim(b" \tchunked \t"), b"chunked");
        assert_eq!(trim(b"   "), b"");
        assert_eq!(trim(b""), b"");
    }
}
