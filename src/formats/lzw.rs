//! TIFF's LZW (compression 5), decoded straight into a strip's rows.
//!
//! TIFF 6.0, section 13: codes of 9 to 12 bits, most significant bit
//! first; 256 clears the table, 257 ends the strip; the code width grows
//! one code early (at 511, 1023 and 2047 entries, "early change").
//!
//! A strip is decoded into one contiguous slice, so every table entry's
//! string is a run of bytes already written there: the string of a new
//! entry is the previous code's string followed by the first byte of the
//! current one, and that byte is the next one written. An entry is
//! therefore a `(start, length)` pair into the output, and decoding a code
//! is one copy from earlier in the same slice (16 bytes at a time for the
//! short strings that dominate camera images), with no string table and no
//! reversal of prefix chains.
//!
//! `weezl` (the `tiff` crate's decoder) streams into buffers of any size
//! and so keeps its own string table; on test_cavity's frames (1280x1024,
//! 171 strips of 6 rows) it took 7.3 ms a frame on one core, this 2.8 ms
//! (the two alternated in one process, 200 times each). `cargo bench
//! --bench detect -- decode` times the whole `decode_image` (strips in
//! parallel on the machine's cores). The tests check this decoder
//! against weezl's on encoded images of every kind and on the real frames.
//!
//! [`check_strip`] answers whether a strip decodes, from the strings'
//! lengths alone, without memory for the rows: the service checks uploads
//! with it before accepting them.

/// Why a strip did not decode to exactly its rows.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct Corrupt;

/// The entries of a full table: 4,096 codes of 12 bits.
const TABLE: usize = 4096;

/// A decoder's table of `(start, length)` entries (32 KiB), kept from
/// strip to strip by the caller: the decoder reads an entry only below
/// the next free code, which it has written since the strip's start or
/// its last clear code, so what earlier strips left in it is never read
/// and it is never cleared (clearing it for each of a frame's 171 strips
/// was a sixth of the decoder's instructions).
pub(crate) struct Table(Box<[(u32, u32); TABLE]>);

impl Table {
    pub(crate) fn new() -> Table {
        Table(Box::new([(0, 0); TABLE]))
    }
}
const CLEAR: usize = 256;
const END: usize = 257;

/// What a strip's strings are written to: the rows ([`Rows`]), or nowhere
/// ([`Lengths`]) when only whether it decodes is asked.
trait Output {
    /// The literal `byte` at `at`.
    fn literal(&mut self, at: usize, byte: u8);
    /// The `length` bytes at `start` (before `at`) again at `at`.
    fn copy(&mut self, start: usize, length: usize, at: usize);
    /// The entry being defined ("KwKwK"): the `length` bytes at `start`,
    /// then the first of them, at `at`.
    fn repeat(&mut self, start: usize, length: usize, at: usize);
}

/// The strip's rows.
struct Rows<'a>(&'a mut [u8]);

impl Output for Rows<'_> {
    #[inline(always)]
    fn literal(&mut self, at: usize, byte: u8) {
        self.0[at] = byte;
    }

    #[inline(always)]
    fn copy(&mut self, start: usize, length: usize, at: usize) {
        let out = &mut *self.0;
        if length <= 16 && at + 16 <= out.len() {
            // The bytes after the string are overwritten later.
            let chunk: [u8; 16] = out[start..start + 16].try_into().expect("16 bytes");
            out[at..at + 16].copy_from_slice(&chunk);
        } else {
            out.copy_within(start..start + length, at);
        }
    }

    #[inline(always)]
    fn repeat(&mut self, start: usize, length: usize, at: usize) {
        self.0.copy_within(start..start + length, at);
        self.0[at + length] = self.0[start];
    }
}

/// Nothing written: every way a strip can fail depends on its codes and
/// its strings' lengths alone.
struct Lengths;

impl Output for Lengths {
    #[inline(always)]
    fn literal(&mut self, _: usize, _: u8) {}
    #[inline(always)]
    fn copy(&mut self, _: usize, _: usize, _: usize) {}
    #[inline(always)]
    fn repeat(&mut self, _: usize, _: usize, _: usize) {}
}

/// Decodes one LZW-compressed strip into `out`, which must come out full:
/// an end code or the end of the input before that, more output than
/// `out` holds, or a code that is not yet in the table is [`Corrupt`].
pub(crate) fn decode_strip(input: &[u8], out: &mut [u8], table: &mut Table) -> Result<(), Corrupt> {
    let n = out.len();
    inflate(input, n, Rows(out), table)
}

/// Whether [`decode_strip`] would decode `input` into exactly `n` bytes,
/// without writing them. It takes about as long as decoding (reading the
/// codes is the work) but no memory for the output: what an upload is
/// checked with before it is accepted.
pub(crate) fn check_strip(input: &[u8], n: usize, table: &mut Table) -> Result<(), Corrupt> {
    inflate(input, n, Lengths, table)
}

/// The decoder, writing to `out`, which holds `n` bytes.
#[inline(always)]
fn inflate(
    input: &[u8],
    n: usize,
    mut out: impl Output,
    Table(table): &mut Table,
) -> Result<(), Corrupt> {
    // (start, length) of each entry's string in the output; only those
    // below `next` are read. After a clear code (and at the strip's start)
    // there is no previous string, and the next code can only be a
    // literal, or clear or end: `next` starts one early, at the end
    // code's number, so that this first code's insertion (of whatever
    // `previous` holds) lands in the entry of the end code, which is never
    // read, and brings `next` to the first entry. So every code inserts,
    // with no test for a previous string. A first code of 258 or more is
    // above `next` and refused, as it must be; the KwKwK case, a code equal
    // to `next`, would be the end code, which is taken first.
    let mut next = END;
    let mut width = 9u32;
    // `next` at which the code width grows: one code early ("early
    // change"), never past 12 bits.
    let mut grow_at = (1 << width) - 1;
    // The next input bits, most significant first; `held` of them valid.
    let mut bits = 0u64;
    let mut held = 0u32;
    let mut read = 0usize;
    let mut written = 0usize;
    // The previous code's string (start, length).
    let mut previous = (0usize, 0usize);
    loop {
        if held < width {
            if let Some(word) = input.get(read..read + 8) {
                // Whole bytes only: the bits after them are the next
                // bytes' own, so the next refill ORs in the same values.
                let word = u64::from_be_bytes(word.try_into().expect("8 bytes"));
                bits |= word >> held;
                let bytes = (63 - held) / 8;
                read += bytes as usize;
                held += bytes * 8;
            } else {
                while held <= 56 && read < input.len() {
                    bits |= u64::from(input[read]) << (56 - held);
                    read += 1;
                    held += 8;
                }
                if held < width {
                    // The input ended without an end code: fine if the
                    // rows are complete (some writers omit it).
                    return if written == n { Ok(()) } else { Err(Corrupt) };
                }
            }
        }
        let code = (bits >> (64 - width)) as usize;
        bits <<= width;
        held -= width;
        if code == CLEAR {
            next = END;
            width = 9;
            grow_at = (1 << width) - 1;
            continue;
        }
        if code == END {
            return if written == n { Ok(()) } else { Err(Corrupt) };
        }
        let length = if code < CLEAR {
            if written >= n {
                return Err(Corrupt);
            }
            out.literal(written, code as u8);
            1
        } else if code < next {
            let (start, length) = table[code];
            let (start, length) = (start as usize, length as usize);
            if written + length > n {
                return Err(Corrupt);
            }
            out.copy(start, length, written);
            length
        } else if code == next {
            // The entry being defined: the previous string and its own
            // first byte.
            let (start, length) = previous;
            if written + length + 1 > n {
                return Err(Corrupt);
            }
            out.repeat(start, length, written);
            length + 1
        } else {
            return Err(Corrupt);
        };
        if next < TABLE {
            let (start, previous_length) = previous;
            table[next] = (start as u32, previous_length as u32 + 1);
            next += 1;
            if next >= grow_at {
                width += 1;
                grow_at = if width < 12 {
                    (1 << width) - 1
                } else {
                    usize::MAX
                };
            }
        }
        previous = (written, length);
        written += length;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encode(samples: &[u8]) -> Vec<u8> {
        weezl::encode::Encoder::with_tiff_size_switch(weezl::BitOrder::Msb, 8)
            .encode(samples)
            .expect("encodes")
    }

    fn weezl_decode(input: &[u8], n: usize) -> Option<Vec<u8>> {
        let mut out = vec![0u8; n];
        let mut decoder = weezl::decode::Decoder::with_tiff_size_switch(weezl::BitOrder::Msb, 8);
        let (mut input, mut done) = (input, 0);
        while done < n {
            let result = decoder.decode_bytes(input, &mut out[done..]);
            done += result.consumed_out;
            input = &input[result.consumed_in..];
            match result.status {
                Ok(weezl::LzwStatus::Ok) if result.consumed_in + result.consumed_out > 0 => {}
                _ if done == n => {}
                _ => return None,
            }
        }
        Some(out)
    }

    /// A small deterministic generator (xorshift), so that the cases are
    /// the same on every run.
    fn noise(seed: u64) -> impl FnMut() -> u64 {
        let mut state = seed.max(1);
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        }
    }

    /// Strips of every kind a camera writes: noise (short strings, many
    /// table clears), smooth gradients and flat runs (long strings beyond
    /// the 16-byte copy, the "KwKwK" case of a code defined by its own
    /// use), and a sparse particle field on a dark background; at sizes
    /// from one byte to several table fills.
    #[test]
    fn strips_decode_as_weezl_decodes_them() {
        let mut random = noise(7);
        let mut cases: Vec<Vec<u8>> = vec![vec![0], vec![255; 3], vec![9; 100_000]];
        for &n in &[1usize, 2, 17, 255, 4_096, 7_680, 65_536, 200_000] {
            cases.push((0..n).map(|_| random() as u8).collect());
            cases.push((0..n).map(|i| (i / 97) as u8).collect());
            cases.push((0..n).map(|_| (random() % 4) as u8).collect());
            cases.push(
                (0..n)
                    .map(|_| match random() % 50 {
                        0 => 200 + (random() % 56) as u8,
                        _ => (random() % 3) as u8,
                    })
                    .collect(),
            );
        }
        for samples in &cases {
            let encoded = encode(samples);
            let mut out = vec![0u8; samples.len()];
            assert_eq!(
                decode_strip(&encoded, &mut out, &mut Table::new()),
                Ok(()),
                "{} bytes",
                samples.len()
            );
            assert_eq!(&out, samples, "{} bytes", samples.len());
            assert_eq!(
                check_strip(&encoded, samples.len(), &mut Table::new()),
                Ok(())
            );
            assert_eq!(
                weezl_decode(&encoded, samples.len()).as_ref(),
                Some(samples)
            );
        }
    }

    /// The real recording's frames (8-bit, 171 LZW strips of 6 rows, the
    /// last of 4)
    /// decode to what weezl makes of them.
    #[test]
    fn the_real_recordings_strips_decode_as_weezl_decodes_them() {
        use tiff::decoder::Decoder;
        use tiff::tags::Tag;
        let folder = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/openptv/test_cavity_recording/img"
        );
        let mut frames = 0;
        // One table for every strip, as `decode_image` keeps one per
        // thread: what a strip leaves in it changes nothing.
        let mut table = Table::new();
        for entry in std::fs::read_dir(folder).expect("the recording") {
            let bytes = std::fs::read(entry.expect("an entry").path()).expect("a frame");
            let mut decoder = Decoder::new(std::io::Cursor::new(&bytes)).expect("a TIFF");
            let (width, height) = decoder.dimensions().expect("dimensions");
            let mut left = width as usize * height as usize;
            let rows = decoder.find_tag_unsigned::<u64>(Tag::RowsPerStrip).unwrap();
            let strip = rows.expect("rows per strip") as usize * width as usize;
            let offsets = decoder.get_tag_u64_vec(Tag::StripOffsets).unwrap();
            let counts = decoder.get_tag_u64_vec(Tag::StripByteCounts).unwrap();
            for (&offset, &count) in offsets.iter().zip(&counts) {
                let input = &bytes[offset as usize..(offset + count) as usize];
                // The last strip holds the rows that are left.
                let strip = strip.min(left);
                left -= strip;
                let expected = weezl_decode(input, strip).expect("weezl decodes it");
                let mut out = vec![0u8; strip];
                assert_eq!(decode_strip(input, &mut out, &mut table), Ok(()));
                assert_eq!(check_strip(input, strip, &mut table), Ok(()));
                assert_eq!(out, expected);
            }
            frames += 1;
        }
        assert_eq!(frames, 16, "test_cavity's 4 cameras x 4 frames");
    }

    /// Cut, grown, bit-flipped and random strips never panic and never
    /// report a strip full that is not: whatever this decoder accepts,
    /// weezl decodes to the same bytes.
    #[test]
    fn corrupt_strips_are_refused_without_panicking() {
        let mut random = noise(11);
        let samples: Vec<u8> = (0..20_000)
            .map(|i| ((i / 13) as u8) ^ (random() % 3) as u8)
            .collect();
        let encoded = encode(&samples);
        let mut out = vec![0u8; samples.len()];
        for cut in [0, 1, 2, encoded.len() / 2, encoded.len() - 3] {
            assert_eq!(
                decode_strip(&encoded[..cut], &mut out, &mut Table::new()),
                Err(Corrupt),
                "cut at {cut}"
            );
        }
        // Asking for more rows than the strip holds.
        let mut longer = vec![0u8; samples.len() + 1];
        assert_eq!(
            decode_strip(&encoded, &mut longer, &mut Table::new()),
            Err(Corrupt)
        );
        assert_eq!(
            check_strip(&encoded, longer.len(), &mut Table::new()),
            Err(Corrupt)
        );
        // And for fewer.
        let mut shorter = vec![0u8; samples.len() - 1];
        assert_eq!(
            decode_strip(&encoded, &mut shorter, &mut Table::new()),
            Err(Corrupt)
        );
        assert_eq!(
            check_strip(&encoded, shorter.len(), &mut Table::new()),
            Err(Corrupt)
        );
        // One table through all trials, as a thread keeps it from strip to
        // strip: a damaged strip's code that is not yet in the table is
        // refused whatever earlier strips left there.
        let mut table = Table::new();
        for trial in 0..2_000 {
            let mut damaged = encoded.clone();
            for _ in 0..1 + trial % 4 {
                let at = random() as usize % damaged.len();
                damaged[at] ^= 1 << (random() % 8);
            }
            if trial % 7 == 0 {
                damaged = (0..random() % 3_000).map(|_| random() as u8).collect();
            }
            let decoded = decode_strip(&damaged, &mut out, &mut table);
            assert_eq!(
                check_strip(&damaged, out.len(), &mut table),
                decoded,
                "trial {trial}"
            );
            if decoded.is_ok() {
                assert_eq!(
                    weezl_decode(&damaged, out.len()).as_ref(),
                    Some(&out),
                    "trial {trial}"
                );
            }
        }
    }
}
