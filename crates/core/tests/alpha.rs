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
