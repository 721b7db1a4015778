//! A scene photographed over an open shutter: its animation sampled into the time steps of
//! a [`MotionMesh`] (node animations, skins and morph targets alike).

use bvhtrace_core::motion::{MAX_TIME_STEPS, MotionMesh};
use bvhtrace_core::{Aabb, Triangle};

use crate::{ErrorKind, Scene, SceneError};

/// How far (relative to the scene's size) a corner may stray from the straight line
/// between two time steps before [`Scene::motion`] adds the steps between them.
pub const SHUTTER_TOLERANCE: f32 = 1e-3;

impl Scene {
    /// The scene's triangles (flattened, world space, in [`Scene::flatten`]'s order) as
    /// they move while the shutter is open, from `open` to `close` seconds: time step 0 is
    /// the pose at `open`, the last the pose at `close`, the others evenly between. It
    /// takes as many steps as keep every corner within [`SHUTTER_TOLERANCE`] of the
    /// scene's diagonal of its path (2, 3, 5, 9, ... up to 129), so curved motion is
    /// followed as closely as straight motion. A scene without animation gives two equal
    /// steps. `open` must be before `close`, both finite.
    pub fn motion(&self, open: f32, close: f32) -> Result<MotionMesh, SceneError> {
        let bad = |what: String| SceneError::new(self.name.clone(), ErrorKind::Invalid(what));
        if !(open.is_finite() && close.is_finite() && open < close) {
            return Err(bad(format!(
                "the shutter must open before it closes, got {open} to {close} seconds"
            )));
        }
        let pose = |k: usize, segments: usize| {
            let t = open + (close - open) * (k as f32 / segments as f32);
            let mut s = self.clone();
            s.set_time(t);
            s.flattened_triangles()
        };
        let mut steps = vec![pose(0, 1)?, pose(1, 1)?];
        let tolerance = SHUTTER_TOLERANCE * diagonal(&steps);
        while 2 * steps.len() - 1 <= MAX_TIME_STEPS {
            let segments = steps.len() - 1;
            let mids = (0..segments)
                .map(|k| pose(2 * k + 1, 2 * segments))
                .collect::<Result<Vec<_>, _>>()?;
            let worst = (0..segments)
                .map(|k| stray(&steps[k], &steps[k + 1], &mids[k]))
                .fold(0.0f32, f32::max);
            if worst <= tolerance {
                break;
            }
            let mut mids = mids.into_iter();
            steps = std::mem::take(&mut steps)
                .into_iter()
                .flat_map(|s| [Some(s), mids.next()])
                .flatten()
                .collect();
        }
        MotionMesh::new(steps).map_err(|e| bad(format!("bad motion: {e}")))
    }
}

/// The diagonal of the box around every step's corners.
fn diagonal(steps: &[Vec<Triangle>]) -> f32 {
    let b = steps
        .iter()
        .flatten()
        .flatten()
        .fold(Aabb::EMPTY, |b, &p| b.union(&Aabb::from_point(p)));
    if b.is_empty() {
        0.0
    } else {
        b.extent().length()
    }
}

/// How far the corners of `mid` are from the midpoints of `a` and `b`'s (the largest).
fn stray(a: &[Triangle], b: &[Triangle], mid: &[Triangle]) -> f32 {
    a.iter()
        .zip(b)
        .zip(mid)
        .flat_map(|((a, b), m)| (0..3).map(move |k| ((a[k] + b[k]) * 0.5).distance(m[k])))
        .fold(0.0, f32::max)
}
