//! The alpha rule's triangle states are conservative: a triangle settled opaque passes at
//! every point sampled over it, one settled transparent fails at every point, under every
//! wrap mode, for random textures and random texture coordinates, many of them on or near
//! the ends of a wrap period or exactly on them.

use bvhtrace_core::alpha::{AlphaMask, TriangleState, Wrap, triangle_state};
use glam::Vec2;

mod common;

#[test]
fn settled_triangles_agree_with_every_sample() {
    let mut rnd = common::xorshift(0xa1fa_5eed);
    let (mut settled, mut tested) = (0, 0);
    for case in 0..3000 {
        let (w, h) = (1 + (rnd() * 9.0) as u32, 1 + (rnd() * 9.0) as u32);
        // Mostly-solid, mostly-empty or mixed textures, so all three states occur.
        let bias = rnd();
        let alpha: Vec<u8> = (0..w * h)
            .map(|_| {
                if rnd() < bias {
                    255
                } else {
                    (rnd() * 100.0) as u8
                }
            })
            .collect();
        let wraps = [Wrap::Repeat, Wrap::ClampToEdge, Wrap::MirroredRepeat];
        let wrap = [wraps[case % 3], wraps[(case / 3) % 3]];
        let mask = AlphaMask {
            alpha: &alpha,
            width: w,
            height: h,
            wrap,
            min_texel: 128,
        };
        // Corners near period ends half the time, small or large triangles.
        let coord = |r: &mut dyn FnMut() -> f32| {
            let k = (r() * 6.0).floor() - 3.0;
            match (r() * 3.0) as u32 {
                0 => k,
                1 => k + (r() - 0.5) * 1e-3,
                _ => k + r(),
            }
        };
        let base = Vec2::new(coord(&mut rnd), coord(&mut rnd));
        let size = if rnd() < 0.5 { 0.05 } else { 0.6 };
        let corner = |r: &mut dyn FnMut() -> f32| base + Vec2::new(r() - 0.5, r() - 0.5) * size;
        let uv = [base, corner(&mut rnd), corner(&mut rnd)];
        let state = triangle_state(&uv, &mask);
        if state == TriangleState::Test {
            tested += 1;
            continue;
        }
        settled += 1;
        for s in 0..=40 {
            for t in 0..=(40 - s) {
                let (u, v) = (s as f32 / 40.0, t as f32 / 40.0);
                assert_eq!(
                    mask.passes(&uv, u, v),
                    state == TriangleState::Opaque,
                    "case {case}: {state:?} but ({u}, {v}) disagrees; uv {uv:?}, {w}x{h}, {wrap:?}"
                );
            }
        }
    }
    assert!(
        settled > 500 && tested > 500,
        "{settled} settled, {tested} tested"
    );
}

/// Micromaps are conservative too: in every micro-triangle settled opaque or transparent,
/// every sampled candidate (the grid of the triangle, and random points) agrees with the
/// texture, under every wrap mode, with textures up to 64 texels a side; and they settle
/// most micro-triangles of a triangle that is tested as a whole.
#[test]
fn micromaps_agree_with_every_sample() {
    use bvhtrace_core::masks::{MICRO_TEST, MaskTriangle, micro_slot, micromap};
    let mut rnd = common::xorshift(0x0a11_ce11);
    let (mut settled, mut all) = (0usize, 0usize);
    for case in 0..400 {
        let (w, h) = (1 + (rnd() * 64.0) as u32, 1 + (rnd() * 64.0) as u32);
        // A disc of kept texels, as a leaf's texture has, with noise at its edge.
        let alpha: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = (
                    (i % w) as f32 / w as f32 - 0.5,
                    (i / w) as f32 / h as f32 - 0.5,
                );
                let d = (x * x + y * y).sqrt() + (rnd() - 0.5) * 0.05;
                if d < 0.35 { 255 } else { (rnd() * 127.0) as u8 }
            })
            .collect();
        let wraps = [Wrap::Repeat, Wrap::ClampToEdge, Wrap::MirroredRepeat];
        let mask = AlphaMask {
            alpha: &alpha,
            width: w,
            height: h,
            wrap: [wraps[case % 3], wraps[(case / 3) % 3]],
            min_texel: 128,
        };
        let o = Vec2::new((rnd() * 4.0).floor() - 2.0, (rnd() * 4.0).floor() - 2.0);
        let s = 0.5 + rnd() * 1.5;
        let uv = [o, o + Vec2::new(s, 0.0), o + Vec2::new(rnd() * s, s)];
        let t = MaskTriangle {
            micro: micromap(&uv, &mask),
            ..MaskTriangle::default()
        };
        let check = |u: f32, v: f32| {
            let state = t.micro_state(micro_slot(u, v));
            if state != MICRO_TEST {
                assert_eq!(
                    mask.passes(&uv, u, v),
                    state == bvhtrace_core::masks::MICRO_OPAQUE,
                    "case {case}: micro state {state} at ({u}, {v}); uv {uv:?}, {w}x{h}"
                );
            }
        };
        for a in 0..=64 {
            for b in 0..=(64 - a) {
                check(a as f32 / 64.0, b as f32 / 64.0);
            }
        }
        for _ in 0..500 {
            let (u, v) = (rnd(), rnd());
            let (u, v) = if u + v > 1.0 {
                (1.0 - u, 1.0 - v)
            } else {
                (u, v)
            };
            check(u, v);
        }
        let slots = 2 * 8 * 8;
        all += slots;
        settled += (0..slots)
            .filter(|&k| t.micro_state(k) != MICRO_TEST)
            .count();
    }
    assert!(
        2 * settled > all,
        "{settled} of {all} micro-triangles settled"
    );
}
