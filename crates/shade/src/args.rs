//! Parsers for the flags the front ends share (`--eye`, `--target`, `--size`), for
//! `clap`'s `value_parser`: errors are sentences naming the value.

use glam::Vec3;

/// Parses the `X,Y,Z` form of the `--eye` and `--target` flags (`bvhtrace render`, the
/// viewer, and the camera line the viewer copies): three finite numbers, spaces around each
/// allowed.
pub fn parse_vec3(s: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("expected three numbers X,Y,Z, got '{s}'"));
    }
    let mut v = [0f32; 3];
    for (slot, p) in v.iter_mut().zip(&parts) {
        *slot = p
            .parse::<f32>()
            .map_err(|_| format!("'{p}' is not a number"))?;
        if !slot.is_finite() {
            return Err(format!("'{p}' is not finite"));
        }
    }
    Ok(Vec3::from(v))
}

/// Parses the `WxH` form of the image and window size flags: two integers of at least 1,
/// with `x` or `X` between them and spaces around each allowed. The caller bounds them.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected WxH, got '{s}'"))?;
    let w: u32 = w
        .trim()
        .parse()
        .map_err(|_| format!("bad width in '{s}'"))?;
    let h: u32 = h
        .trim()
        .parse()
        .map_err(|_| format!("bad height in '{s}'"))?;
    if w == 0 || h == 0 {
        return Err(format!(
            "the width and height must be at least 1, got '{s}'"
        ));
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_flags_parse_and_refuse_clearly() {
        assert_eq!(parse_vec3("1, -2.5,3e2"), Ok(Vec3::new(1.0, -2.5, 300.0)));
        assert_eq!(
            parse_vec3("1,2"),
            Err("expected three numbers X,Y,Z, got '1,2'".into())
        );
        assert_eq!(parse_vec3("1,a,2"), Err("'a' is not a number".into()));
        assert_eq!(parse_vec3("1,inf,2"), Err("'inf' is not finite".into()));
        assert_eq!(parse_size("640x480"), Ok((640, 480)));
        assert_eq!(parse_size(" 64 X 48 "), Ok((64, 48)));
        assert_eq!(parse_size("640"), Err("expected WxH, got '640'".into()));
        assert_eq!(parse_size("-1x5"), Err("bad width in '-1x5'".into()));
        assert_eq!(parse_size("5xq"), Err("bad height in '5xq'".into()));
        assert!(parse_size("0x5").is_err() && parse_size("5x0").is_err());
    }
}
