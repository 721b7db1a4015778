//! A scene photographed over an open shutter: its animation sampled into the time steps of
//! a [`MotionMesh`] (node animations, skins and morph targets alike).

use bvhtrace_core::motion::{MAX_TIME_STEPS, MotionMesh, MovingInstance};
use std::borrow::Cow;

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
        self.check_shutter(open, close)?;
        // One copy posed again and again: `set_time` places everything from the animation
        // afresh.
        let posed = std::cell::RefCell::new(self.clone());
        let pose = |f: f32| {
            let mut s = posed.borrow_mut();
            s.set_time(open + (close - open) * f);
            s.flattened_triangles()
        };
        let steps = time_steps(pose, |tris: &Vec<Triangle>| {
            Cow::Borrowed(tris.as_flattened())
        })?;
        MotionMesh::new(steps).map_err(|e| self.invalid(format!("bad motion: {e}")))
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
        self.check_shutter(open, close)?;
        if self
            .animation
            .as_ref()
            .is_some_and(|a| !a.skins.is_empty() || !a.morphs.is_empty())
        {
            return Err(self.invalid(
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
        let pose = |f: f32| Ok(self.instance_transforms_at(open + (close - open) * f));
        // Each instance's mesh box, placed.
        let steps = time_steps(pose, |m: &Vec<Mat4>| {
            (corners.iter().zip(m))
                .flat_map(|(c, m)| c.map(|p| m.transform_point3(p)))
                .collect()
        })?;
        let instances = (self.instances.iter().enumerate())
            .map(|(i, inst)| MovingInstance {
                mesh: inst.mesh,
                transforms: steps.iter().map(|s| s[i]).collect(),
            })
            .collect();
        Ok((meshes, instances))
    }
}

impl Scene {
    /// Refuses a shutter that is not open: `open` before `close`, both finite.
    fn check_shutter(&self, open: f32, close: f32) -> Result<(), SceneError> {
        if open.is_finite() && close.is_finite() && open < close {
            return Ok(());
        }
        Err(self.invalid(format!(
            "the shutter must open before it closes, got {open} to {close} seconds"
        )))
    }

    fn invalid(&self, what: String) -> SceneError {
        SceneError::new(self.name.clone(), ErrorKind::Invalid(what))
    }
}

/// Poses at evenly spaced time steps over the shutter (`pose(f)` is the pose `f` of the way
/// through it): the ends, then the steps doubled (3, 5, 9, ... up to [`MAX_TIME_STEPS`])
/// while the `points` of some segment's middle pose stray more than
/// [`SHUTTER_TOLERANCE`] of the first pose's diagonal from the midpoints of its ends'.
fn time_steps<T>(
    pose: impl Fn(f32) -> Result<T, SceneError>,
    points: impl for<'a> Fn(&'a T) -> Cow<'a, [Vec3]>,
) -> Result<Vec<T>, SceneError> {
    let at = |k: usize, segments: usize| pose(k as f32 / segments as f32);
    let mut steps = vec![at(0, 1)?, at(1, 1)?];
    let tolerance = SHUTTER_TOLERANCE * diagonal(&points(&steps[0]));
    while 2 * steps.len() - 1 <= MAX_TIME_STEPS {
        let segments = steps.len() - 1;
        let mids = (0..segments)
            .map(|k| at(2 * k + 1, 2 * segments))
            .collect::<Result<Vec<_>, _>>()?;
        let worst = (0..segments)
            .map(|k| {
                stray(
                    &points(&steps[k]),
                    &points(&steps[k + 1]),
                    &points(&mids[k]),
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
    Ok(steps)
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
