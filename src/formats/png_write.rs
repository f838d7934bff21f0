//! PNG encoding for `render`, which computes pictures as plain RGB
//! buffers. Encoding is deterministic (fixed compression and filter), so
//! the same picture gives the same bytes.

/// Encodes an 8-bit RGB picture (`width × height × 3` bytes, rows top to
/// bottom) as PNG bytes.
pub fn encode_rgb(width: u32, height: u32, rgb: &[u8]) -> std::result::Result<Vec<u8>, String> {
    if width == 0 || height == 0 {
        return Err(format!(
            "a picture needs at least one pixel, got {width}×{height}"
        ));
    }
    let expected = (width as u64)
        .checked_mul(height as u64)
        .and_then(|n| n.checked_mul(3));
    if expected != Some(rgb.len() as u64) {
        return Err(format!(
            "{width}×{height} RGB needs {} bytes, got {}",
            expected.map_or("too many".to_string(), |n| n.to_string()),
            rgb.len()
        ));
    }
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Best);
    encoder.set_filter(png::FilterType::Paeth);
    encoder.set_adaptive_filter(png::AdaptiveFilterType::NonAdaptive);
    let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
    writer.write_image_data(rgb).map_err(|e| e.to_string())?;
    writer.finish().map_err(|e| e.to_string())?;
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_every_pixel_and_is_deterministic() {
        let (w, h) = (5u32, 3u32);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 17 % 251) as u8).collect();
        let bytes = encode_rgb(w, h, &rgb).unwrap();
        assert_eq!(bytes, encode_rgb(w, h, &rgb).unwrap());
        let decoder = png::Decoder::new(std::io::Cursor::new(&bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut out = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut out).unwrap();
        assert_eq!((info.width, info.height), (w, h));
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(&out[..info.buffer_size()], &rgb[..]);
    }

    #[test]
    fn wrong_buffer_size_and_empty_pictures_are_errors() {
        assert!(encode_rgb(2, 2, &[0; 11])
            .unwrap_err()
            .contains("needs 12 bytes"));
        assert!(encode_rgb(0, 2, &[]).is_err());
    }
}
