//! A scene photographed over an open shutter: its animation sampled into the time steps of
//! a [`MotionMesh`] (node animations, skins and morph targets alike).

use bvhtrace_core::motion::{MAX_TIME_STEPS, MotionMesh, MovingInstance};
use bvhtrace_core::{Aabb, Triangle};
use glam::{Mat4, Vec3};

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
        let tolerance = SHUTTER_TOLERANCE * diagonal(steps[0].as_flattened());
        while 2 * steps.len() - 1 <= MAX_TIME_STEPS {
            let segments = steps.len() - 1;
            let mids = (0..segments)
                .map(|k| pose(2 * k + 1, 2 * segments))
                .collect::<Result<Vec<_>, _>>()?;
            let worst = (0..segments)
                .map(|k| {
                    stray(
                        steps[k].as_flattened(),
                        steps[k + 1].as_flattened(),
                        mids[k].as_flattened(),
                    )
                })
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

impl Scene {
    /// The scene over the shutter in two levels: each mesh's triangles (object space) and
    /// each instance's transforms at time steps evenly from `open` to `close` seconds, as
    /// many as keep every corner of each instance's mesh box within [`SHUTTER_TOLERANCE`]
    /// of the scene's diagonal of its path between steps (as [`Scene::motion`]). Only for
    /// scenes whose animation moves instances without deforming meshes: a skinned or
    /// morphed scene is refused (trace it flattened, [`Scene::motion`]).
    pub fn moving_instances(
        &self,
        open: f32,
        close: f32,
    ) -> Result<(Vec<Vec<Triangle>>, Vec<MovingInstance>), SceneError> {
        let bad = |what: String| SceneError::new(self.name.clone(), ErrorKind::Invalid(what));
        if !(open.is_finite() && close.is_finite() && open < close) {
            return Err(bad(format!(
                "the shutter must open before it closes, got {open} to {close} seconds"
            )));
        }
        if self
            .animation
            .as_ref()
            .is_some_and(|a| !a.skins.is_empty() || !a.morphs.is_empty())
        {
            return Err(bad(
                "its animation deforms meshes (skins or morph targets): trace it flattened".into(),
            ));
        }
        let meshes: Vec<Vec<Triangle>> = (self.meshes.iter())
            .map(|m| {
                m.indices
                    .iter()
                    .map(|t| t.map(|i| m.positions[i as usize]))
                    .collect()
            })
            .collect();
        let corners: Vec<[Vec3; 8]> = self
            .instances
            .iter()
            .map(|i| box_corners(&meshes[i.mesh]))
            .collect();
        let pose = |k: usize, segments: usize| {
            self.instance_transforms_at(open + (close - open) * (k as f32 / segments as f32))
        };
        let mut steps = vec![pose(0, 1), pose(1, 1)];
        let placed = |m: &[Mat4]| -> Vec<Vec3> {
            (corners.iter().zip(m))
                .flat_map(|(c, m)| c.map(|p| m.transform_point3(p)))
                .collect()
        };
        let tolerance = SHUTTER_TOLERANCE * diagonal(&placed(&steps[0]));
        while 2 * steps.len() - 1 <= MAX_TIME_STEPS {
            let segments = steps.len() - 1;
            let mids: Vec<Vec<Mat4>> = (0..segments)
                .map(|k| pose(2 * k + 1, 2 * segments))
                .collect();
            let worst = (0..segments)
                .map(|k| {
                    stray(
                        &placed(&steps[k]),
                        &placed(&steps[k + 1]),
                        &placed(&mids[k]),
                    )
                })
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
        let instances = (self.instances.iter().enumerate())
            .map(|(i, inst)| MovingInstance {
                mesh: inst.mesh,
                transforms: steps.iter().map(|s| s[i]).collect(),
            })
            .collect();
        Ok((meshes, instances))
    }
}

/// The eight corners of the box around `tris`.
fn box_corners(tris: &[Triangle]) -> [Vec3; 8] {
    let b = tris
        .iter()
        .fold(Aabb::EMPTY, |b, t| b.union(&Aabb::from_triangle(t)));
    let (lo, hi) = if b.is_empty() {
        (Vec3::ZERO, Vec3::ZERO)
    } else {
        (b.min, b.max)
    };
    std::array::from_fn(|i| {
        Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    })
}

/// The diagonal of the box around `points`.
fn diagonal(points: &[Vec3]) -> f32 {
    let b = (points.iter()).fold(Aabb::EMPTY, |b, &p| b.union(&Aabb::from_point(p)));
    if b.is_empty() {
        0.0
    } else {
        b.extent().length()
    }
}

/// How far the points of `mid` are from the midpoints of `a`'s and `b`'s (the largest).
fn stray(a: &[Vec3], b: &[Vec3], mid: &[Vec3]) -> f32 {
    (a.iter().zip(b).zip(mid))
        .map(|((a, b), m)| ((*a + *b) * 0.5).distance(*m))
        .fold(0.0, f32::max)
}
