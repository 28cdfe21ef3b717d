//! The preview's canvas: an 8-bit RGB image, written as PNG by the `png` crate.
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

    /// The PNG file (8-bit RGB; the `png` crate's default filtering and compression: a
    /// mostly flat preview strip shrinks ~50x).
    pub fn encode(&self) -> Result<Vec<u8>, png::EncodingError> {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(&self.rgb)?;
        w.finish()?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(bytes: &[u8]) -> (png::OutputInfo, Vec<u8>) {
        let mut r = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        let info = r.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info, buf)
    }

    #[test]
    fn pixels_round_trip() {
        let mut img = Image::new(5, 3, [10, 20, 30]);
        img.put(4, 2, [255, 0, 0]);
        img.put(-1, 0, [1, 1, 1]); // outside: ignored
        img.put(5, 0, [1, 1, 1]);
        let (info, rgb) = decode(&img.encode().unwrap());
        assert_eq!(
            (info.width, info.height, info.color_type, info.bit_depth),
            (5, 3, png::ColorType::Rgb, png::BitDepth::Eight)
        );
        assert_eq!(rgb, img.rgb);
        assert_eq!(&rgb[3 * 14..], [255, 0, 0], "the last pixel");
        assert_eq!(&rgb[..3], [10, 20, 30], "put outside the image changed nothing");
    }

    #[test]
    fn flat_images_compress() {
        // A flat 1000x300 image is a few KB, not 900 KB.
        let png = Image::new(1000, 300, [240, 240, 235]).encode().unwrap();
        assert!(png.len() < 10_000, "{} bytes", png.len());
    }
}
