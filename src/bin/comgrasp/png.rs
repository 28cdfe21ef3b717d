//! A minimal PNG writer: 8-bit RGB, no interlacing, every scanline with filter 0 (None),
//! the zlib stream compressed by a tiny fixed-Huffman deflate ([`deflate`]).
//!
//! Why not stored blocks: a preview strip is mostly flat background, which stored blocks
//! would keep at full size (~1.5 MB for 1536×320); fixed Huffman codes with two kinds of
//! back-reference (the pixel to the left, the pixel above) shrink it ~50× with no tables to
//! build or transmit. Written by hand to keep the crate's dependency set unchanged.
use crate::checksum::{adler32, crc32, crc32_update};

/// An 8-bit RGB image, rows top to bottom, `rgb.len() == 3 * width * height`.
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Image {
    /// A `width × height` image filled with `colour`.
    pub fn new(width: u32, height: u32, colour: [u8; 3]) -> Image {
        let n = width as usize * height as usize;
        Image { width, height, rgb: colour.repeat(n) }
    }

    /// Sets one pixel; coordinates outside the image are ignored (callers clip by drawing).
    pub fn put(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return;
        }
        let at = 3 * (y as usize * self.width as usize + x as usize);
        self.rgb[at..at + 3].copy_from_slice(&colour);
    }

    /// The PNG file: signature, IHDR, one IDAT, IEND.
    pub fn encode(&self) -> Vec<u8> {
        let row = 3 * self.width as usize;
        let mut raw = Vec::with_capacity((row + 1) * self.height as usize);
        for line in self.rgb.chunks_exact(row.max(1)).take(self.height as usize) {
            raw.push(0); // filter type None
            raw.extend_from_slice(line);
        }
        let mut ihdr = Vec::with_capacity(13);
        ihdr.extend_from_slice(&self.width.to_be_bytes());
        ihdr.extend_from_slice(&self.height.to_be_bytes());
        // bit depth 8, colour type 2 (RGB), compression 0, filter 0, interlace 0
        ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);

        let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
        chunk(&mut out, b"IHDR", &ihdr);
        chunk(&mut out, b"IDAT", &zlib(&raw, row + 1));
        chunk(&mut out, b"IEND", &[]);
        out
    }
}

/// length, type, data, CRC of type + data.
fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    out.extend_from_slice(&crc32_update(crc32(kind), data).to_be_bytes());
}

/// A zlib stream (RFC 1950): header, deflate data, Adler-32 of the raw bytes.
/// `stride` is the scanline length: the distance of "the pixel above" back-references.
fn zlib(raw: &[u8], stride: usize) -> Vec<u8> {
    // CMF 0x78: deflate, 32 KiB window; FLG 0x01: no dictionary, "fastest" level, and
    // (0x78 * 256 + 0x01) % 31 == 0 as the header check requires.
    let mut out = vec![0x78, 0x01];
    out.extend_from_slice(&deflate(raw, stride));
    out.extend_from_slice(&adler32(raw).to_be_bytes());
    out
}

/// Bits into bytes, least significant bit first (RFC 1951 §3.1.1).
struct BitWriter {
    out: Vec<u8>,
    acc: u64,
    n: u32,
}

impl BitWriter {
    /// Writes the low `n` bits of `v`, LSB first (how deflate packs extra bits and headers).
    fn bits(&mut self, v: u32, n: u32) {
        self.acc |= (v as u64) << self.n;
        self.n += n;
        while self.n >= 8 {
            self.out.push(self.acc as u8);
            self.acc >>= 8;
            self.n -= 8;
        }
    }

    /// Writes a Huffman code of `n` bits, most significant bit first (codes are defined
    /// MSB-first but packed into the LSB-first stream).
    fn code(&mut self, code: u32, n: u32) {
        let rev = code.reverse_bits() >> (32 - n);
        self.bits(rev, n);
    }

    fn finish(mut self) -> Vec<u8> {
        if self.n > 0 {
            self.out.push(self.acc as u8);
        }
        self.out
    }
}

/// Longest and shortest deflate match, and the window (largest distance).
const MAX_MATCH: usize = 258;
const MIN_MATCH: usize = 3;
const WINDOW: usize = 32_768;

const LENGTH_BASE: [u16; 29] =
    [3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131, 163, 195, 227, 258];
const LENGTH_EXTRA: [u8; 29] = [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 5, 5, 5, 5, 0];
const DIST_BASE: [u16; 30] = [
    1, 2, 3, 4, 5, 7, 9, 13, 17, 25, 33, 49, 65, 97, 129, 193, 257, 385, 513, 769, 1025, 1537, 2049, 3073, 4097, 6145,
    8193, 12289, 16385, 24577,
];
const DIST_EXTRA: [u8; 30] =
    [0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9, 10, 10, 11, 11, 12, 12, 13, 13];

/// The fixed literal/length code of symbol `s` (0..=287), RFC 1951 §3.2.6.
fn fixed_litlen(w: &mut BitWriter, s: u32) {
    match s {
        0..=143 => w.code(0x30 + s, 8),
        144..=255 => w.code(0x190 + (s - 144), 9),
        256..=279 => w.code(s - 256, 7),
        _ => w.code(0xC0 + (s - 280), 8),
    }
}

/// One fixed-Huffman deflate block holding all of `data`. Matches are searched only at
/// distances 3 (the previous RGB pixel) and `stride` (the pixel above), greedily: that
/// captures the runs and repeated rows a line drawing consists of, in linear time.
pub fn deflate(data: &[u8], stride: usize) -> Vec<u8> {
    let mut w = BitWriter { out: Vec::with_capacity(data.len() / 16 + 64), acc: 0, n: 0 };
    w.bits(1, 1); // BFINAL
    w.bits(1, 2); // BTYPE 01: fixed Huffman
    let candidates = [3, stride];
    let mut i = 0;
    while i < data.len() {
        let limit = MAX_MATCH.min(data.len() - i);
        let (mut best_len, mut best_dist) = (0, 0);
        for &d in &candidates {
            if d == 0 || d > i || d > WINDOW {
                continue;
            }
            let len = (0..limit).take_while(|&k| data[i + k] == data[i + k - d]).count();
            if len > best_len {
                (best_len, best_dist) = (len, d);
            }
        }
        if best_len >= MIN_MATCH {
            let li = LENGTH_BASE.iter().rposition(|&b| b as usize <= best_len).expect("len >= 3");
            fixed_litlen(&mut w, 257 + li as u32);
            w.bits((best_len - LENGTH_BASE[li] as usize) as u32, LENGTH_EXTRA[li] as u32);
            let di = DIST_BASE.iter().rposition(|&b| b as usize <= best_dist).expect("dist >= 1");
            w.code(di as u32, 5);
            w.bits((best_dist - DIST_BASE[di] as usize) as u32, DIST_EXTRA[di] as u32);
            i += best_len;
        } else {
            fixed_litlen(&mut w, data[i] as u32);
            i += 1;
        }
    }
    fixed_litlen(&mut w, 256); // end of block
    w.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Splits a PNG into (type, data) chunks, checking every CRC.
    fn chunks(png: &[u8]) -> Vec<([u8; 4], Vec<u8>)> {
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
        let mut at = 8;
        let mut out = Vec::new();
        while at < png.len() {
            let len = u32::from_be_bytes(png[at..at + 4].try_into().unwrap()) as usize;
            let kind: [u8; 4] = png[at + 4..at + 8].try_into().unwrap();
            let data = png[at + 8..at + 8 + len].to_vec();
            let crc = u32::from_be_bytes(png[at + 8 + len..at + 12 + len].try_into().unwrap());
            assert_eq!(crc, crc32(&png[at + 4..at + 8 + len]), "CRC of {kind:?}");
            out.push((kind, data));
            at += 12 + len;
        }
        out
    }

    #[test]
    fn structure_and_header() {
        let mut img = Image::new(5, 3, [10, 20, 30]);
        img.put(4, 2, [255, 0, 0]);
        img.put(-1, 0, [1, 1, 1]); // outside: ignored
        img.put(5, 0, [1, 1, 1]);
        let png = img.encode();
        let c = chunks(&png);
        let kinds: Vec<&[u8; 4]> = c.iter().map(|(k, _)| k).collect();
        assert_eq!(kinds, [b"IHDR", b"IDAT", b"IEND"]);
        assert_eq!(c[0].1, [0, 0, 0, 5, 0, 0, 0, 3, 8, 2, 0, 0, 0]);
        let z = &c[1].1;
        assert_eq!((z[0], z[1]), (0x78, 0x01));
        assert_eq!(((z[0] as u32) << 8 | z[1] as u32) % 31, 0);
        let mut raw = Vec::new();
        for y in 0..3 {
            raw.push(0);
            raw.extend_from_slice(&img.rgb[y * 15..y * 15 + 15]);
        }
        assert_eq!(&z[z.len() - 4..], adler32(&raw).to_be_bytes());
        assert!(c[2].1.is_empty());
    }

    #[test]
    fn flat_images_compress() {
        // The back-references do their job: a flat 1000×300 image is a few KB, not 900 KB.
        let png = Image::new(1000, 300, [240, 240, 235]).encode();
        assert!(png.len() < 10_000, "{} bytes", png.len());
    }

    #[test]
    fn fixed_codes_of_known_symbols() {
        // 'a' (97) is the 8-bit code 0x30 + 97 = 0x91 = 10010001, reversed into the LSB
        // stream after the 3 header bits 1, 1, 0.
        let out = deflate(b"a", 1);
        // bits in stream order: 1 10 | 10010001 | 0000000 (end of block)
        let bits: Vec<u8> = out.iter().flat_map(|b| (0..8).map(move |i| (b >> i) & 1)).collect();
        assert_eq!(&bits[..3], [1, 1, 0]);
        assert_eq!(&bits[3..11], [1, 0, 0, 1, 0, 0, 0, 1]);
        assert_eq!(&bits[11..18], [0; 7]);
    }
}
