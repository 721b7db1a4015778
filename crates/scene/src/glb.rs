//! The GLB container: a 12-byte header, a JSON chunk and an optional BIN chunk.
//! Parsed here (not by the gltf crate) so that every malformed container gets a precise
//! message and nothing is read past the end of the file.

use crate::error::ErrorKind;

/// GLB magic, `"glTF"` as bytes.
pub(crate) const MAGIC: &[u8; 4] = b"glTF";
/// Chunk type of the JSON chunk (`"JSON"` little-endian).
pub(crate) const CHUNK_JSON: u32 = 0x4E4F_534A;
/// Chunk type of the binary chunk (`"BIN\0"` little-endian).
pub(crate) const CHUNK_BIN: u32 = 0x004E_4942;

/// The chunks of a GLB file, borrowed from its bytes.
pub(crate) struct Glb<'a> {
    /// The JSON chunk's payload.
    pub json: &'a [u8],
    /// The BIN chunk's payload, if the file has one.
    pub bin: Option<&'a [u8]>,
    /// Non-fatal oddities (trailing bytes, unknown chunks).
    pub warnings: Vec<String>,
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    let s = b.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

/// The first bytes of a file as printable text with escapes, for error messages.
pub(crate) fn describe_magic(bytes: &[u8]) -> String {
    bytes
        .iter()
        .take(4)
        .flat_map(|&b| std::ascii::escape_default(b))
        .map(char::from)
        .collect()
}

/// Splits a GLB file into its chunks, checking every length against the file.
pub(crate) fn parse(bytes: &[u8]) -> Result<Glb<'_>, ErrorKind> {
    if bytes.len() < 12 {
        if bytes.len() >= 4 && &bytes[..4] != MAGIC {
            return Err(ErrorKind::BadMagic {
                found: describe_magic(bytes),
            });
        }
        return Err(ErrorKind::Truncated(format!(
            "the GLB header needs 12 bytes, the file has {}",
            bytes.len()
        )));
    }
    if &bytes[..4] != MAGIC {
        return Err(ErrorKind::BadMagic {
            found: describe_magic(bytes),
        });
    }
    let version = u32_at(bytes, 4).unwrap_or(0);
    if version != 2 {
        return Err(ErrorKind::Glb(format!(
            "GLB version {version} (only version 2, glTF 2.0, is supported)"
        )));
    }
    let declared = u32_at(bytes, 8).unwrap_or(0) as usize;
    let mut warnings = Vec::new();
    if declared > bytes.len() {
        return Err(ErrorKind::Truncated(format!(
            "the GLB header says the file is {declared} bytes, it has {}",
            bytes.len()
        )));
    }
    if declared < 20 {
        return Err(ErrorKind::Glb(format!(
            "the GLB header says the file is {declared} bytes, too short for a JSON chunk"
        )));
    }
    if declared < bytes.len() {
        warnings.push(format!(
            "{} bytes after the end of the GLB data (the header says {declared} bytes) were ignored",
            bytes.len() - declared
        ));
    }
    let bytes = &bytes[..declared];

    let mut at = 12usize;
    let mut json = None;
    let mut bin = None;
    let mut chunk_no = 0usize;
    while at < bytes.len() {
        let (Some(len), Some(kind)) = (u32_at(bytes, at), u32_at(bytes, at + 4)) else {
            return Err(ErrorKind::Truncated(format!(
                "chunk {chunk_no} header at byte {at} needs 8 bytes, the GLB data has {}",
                bytes.len() - at
            )));
        };
        let start = at + 8;
        let end = start.saturating_add(len as usize);
        if end > bytes.len() {
            let what = match kind {
                CHUNK_JSON => "the JSON chunk".to_string(),
                CHUNK_BIN => "the BIN chunk".to_string(),
                _ => format!("chunk {chunk_no}"),
            };
            return Err(ErrorKind::Truncated(format!(
                "{what} needs {len} bytes after byte {start}, the GLB data has {}",
                bytes.len() - start
            )));
        }
        let data = &bytes[start..end];
        match (chunk_no, kind) {
            (0, CHUNK_JSON) => json = Some(data),
            (0, _) => {
                return Err(ErrorKind::Glb(format!(
                    "the first chunk must be JSON (type 0x4E4F534A), found type {kind:#010x}"
                )));
            }
            (1, CHUNK_BIN) => bin = Some(data),
            (_, CHUNK_JSON) => {
                return Err(ErrorKind::Glb(format!(
                    "chunk {chunk_no} is a second JSON chunk"
                )));
            }
            (_, CHUNK_BIN) => {
                warnings.push(format!(
                    "chunk {chunk_no} is a second BIN chunk and was ignored"
                ));
            }
            (_, _) => warnings.push(format!(
                "chunk {chunk_no} has unknown type {kind:#010x} and was ignored"
            )),
        }
        chunk_no += 1;
        // Chunks are 4-byte aligned; tolerate files that are not.
        at = end;
    }
    let json = json.ok_or_else(|| ErrorKind::Glb("the file has no JSON chunk".into()))?;
    Ok(Glb {
        json,
        bin,
        warnings,
    })
}

/// Assembles a GLB file from its JSON text and binary payload, padding both chunks to
/// 4 bytes (JSON with spaces, BIN with zeros). An empty `bin` writes no BIN chunk.
pub(crate) fn assemble(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let json_len = json.len() + pad(json.len());
    let bin_len = bin.len() + pad(bin.len());
    let total = 12 + 8 + json_len + if bin.is_empty() { 0 } else { 8 + bin_len };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    if !bin.is_empty() {
        out.extend_from_slice(&(bin_len as u32).to_le_bytes());
        out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
        out.extend_from_slice(bin);
        out.resize(out.len() + pad(bin.len()), 0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_truncation() {
        let glb = assemble(br#"{"asset":{"version":"2.0"}}"#, &[1, 2, 3]);
        let parsed = parse(&glb).expect("valid GLB");
        assert!(parsed.json.starts_with(b"{"));
        assert_eq!(&parsed.bin.expect("bin")[..3], &[1, 2, 3]);
        for n in 0..glb.len() {
            assert!(parse(&glb[..n]).is_err(), "truncated to {n} bytes");
        }
        let mut bad = glb.clone();
        bad[0] = b'x';
        assert!(matches!(parse(&bad), Err(ErrorKind::BadMagic { .. })));
    }
}
