//! Saving screenshots.

use std::path::Path;

use eframe::egui;

/// Checks, before any work, that a PNG can be created at `path`: it names a file (not a
/// folder) in an existing folder.
pub fn check_writable(path: &Path) -> Result<(), String> {
    if path.file_name().is_none() || path.is_dir() {
        return Err(format!("{}: not a file path", path.display()));
    }
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() && !d.is_dir() => Err(format!(
            "cannot write {}: the folder {} does not exist",
            path.display(),
            d.display()
        )),
        _ => Ok(()),
    }
}

/// `img` as RGB8 bytes, with its width and height.
fn rgb_of(img: &egui::ColorImage) -> Result<(Vec<u8>, u32, u32), String> {
    let [w, h] = img.size;
    let (w32, h32) = (
        u32::try_from(w).map_err(|_| "the image is too wide".to_string())?,
        u32::try_from(h).map_err(|_| "the image is too tall".to_string())?,
    );
    if w == 0 || h == 0 {
        return Err("the screenshot is empty".into());
    }
    let mut rgb = Vec::with_capacity(w * h * 3);
    for c in &img.pixels {
        let [r, g, b, _] = c.to_srgba_unmultiplied();
        rgb.extend_from_slice(&[r, g, b]);
    }
    Ok((rgb, w32, h32))
}

/// `img` as the bytes of an RGB PNG file (what a page sends where a program writes a file).
pub fn encode_png(img: &egui::ColorImage) -> Result<Vec<u8>, String> {
    use image::ImageEncoder;
    let (rgb, w, h) = rgb_of(img)?;
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&rgb, w, h, image::ExtendedColorType::Rgb8)
        .map_err(|e| format!("encoding the screenshot: {e}"))?;
    Ok(out)
}

/// Writes `img` as an RGB PNG to `path` atomically: into a temporary file in the same
/// folder, then renamed over `path`, so a reader never sees a partial file. The temporary
/// file is removed on failure.
pub fn write_png_atomic(path: &Path, img: &egui::ColorImage) -> Result<(), String> {
    let (rgb, w32, h32) = rgb_of(img)?;
    let name = path
        .file_name()
        .ok_or_else(|| format!("{}: not a file path", path.display()))?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = image::save_buffer_with_format(
        &tmp,
        &rgb,
        w32,
        h32,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| format!("{}: {e}", tmp.display()))
    .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display())));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_and_refuses() {
        let dir = std::env::temp_dir().join(format!("bvhtrace-viewer-png-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let img = egui::ColorImage::new([3, 2], vec![egui::Color32::from_rgb(10, 20, 30); 6]);
        let p = dir.join("a.png");
        write_png_atomic(&p, &img).expect("writes");
        let back = image::open(&p).expect("reads").to_rgb8();
        assert_eq!(back.dimensions(), (3, 2));
        assert_eq!(back.get_pixel(2, 1).0, [10, 20, 30]);
        // No temporary file is left behind.
        let left: Vec<_> = std::fs::read_dir(&dir)
            .expect("lists")
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
            .collect();
        assert!(left.is_empty());
        assert!(write_png_atomic(&dir.join("missing/b.png"), &img).is_err());
        assert!(check_writable(&dir.join("missing/b.png")).is_err());
        assert!(check_writable(&dir).is_err());
        assert!(check_writable(&dir.join("b.png")).is_ok());
        assert!(check_writable(Path::new("relative.png")).is_ok());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
