//! Files the CLI writes: checked before any work, written atomically; and its progress
//! bars.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// A file that appears at `path` only when complete: data goes to a temporary file in the
/// same folder, renamed over `path` at the end. Creating it checks that the folder is
/// writable, so a bad path fails before any work is done.
pub struct AtomicFile {
    path: PathBuf,
    tmp: PathBuf,
    file: Option<File>,
}

impl AtomicFile {
    /// Reserves `path` (creates the temporary file now).
    pub fn create(path: &Path) -> Result<Self> {
        if path.is_dir() {
            bail!("{}: is a folder, not a file name", path.display());
        }
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = path
            .file_name()
            .with_context(|| format!("{}: not a file name", path.display()))?;
        let tmp = dir.join(format!(
            ".{}.{}.tmp",
            name.to_string_lossy(),
            std::process::id()
        ));
        let file =
            File::create(&tmp).with_context(|| format!("{}: cannot write here", path.display()))?;
        Ok(AtomicFile {
            path: path.to_path_buf(),
            tmp,
            file: Some(file),
        })
    }

    /// Writes all bytes and moves the file into place.
    pub fn finish_with_bytes(mut self, bytes: &[u8]) -> Result<()> {
        let mut f = self.file.take().context("file already finished")?;
        f.write_all(bytes)
            .and_then(|_| f.sync_all())
            .with_context(|| format!("{}: write failed", self.path.display()))?;
        drop(f);
        self.commit()
    }

    /// Moves the (already written) temporary file into place.
    pub fn commit(mut self) -> Result<()> {
        self.file = None;
        std::fs::rename(&self.tmp, &self.path).with_context(|| {
            format!(
                "{}: cannot move the finished file into place",
                self.path.display()
            )
        })?;
        self.tmp = PathBuf::new();
        Ok(())
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if !self.tmp.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Where JSON goes: stdout for `-`, else a file reserved now.
pub enum JsonOut {
    Stdout,
    File(AtomicFile),
}

impl JsonOut {
    /// Reserves the destination.
    pub fn create(spec: &str) -> Result<Self> {
        if spec == "-" {
            Ok(JsonOut::Stdout)
        } else {
            Ok(JsonOut::File(AtomicFile::create(Path::new(spec))?))
        }
    }

    /// Writes the value, pretty-printed.
    pub fn write(self, v: &serde_json::Value) -> Result<()> {
        let text = serde_json::to_string_pretty(v)? + "\n";
        match self {
            JsonOut::Stdout => {
                std::io::stdout().write_all(text.as_bytes())?;
                Ok(())
            }
            JsonOut::File(f) => f.finish_with_bytes(text.as_bytes()),
        }
    }
}

/// Encodes an RGB image as PNG and writes it atomically.
pub fn write_png(file: AtomicFile, w: u32, h: u32, rgb: Vec<u8>) -> Result<()> {
    let img = image::RgbImage::from_raw(w, h, rgb).context("image buffer has the wrong size")?;
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .context("PNG encoding failed")?;
    file.finish_with_bytes(&bytes)
}

/// A progress bar of `len` steps on stderr, drawn by `template` (indicatif's syntax; the
/// default bar if the template does not parse).
pub fn progress_bar(len: u64, template: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new(len);
    pb.set_style(
        indicatif::ProgressStyle::with_template(template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb
}
