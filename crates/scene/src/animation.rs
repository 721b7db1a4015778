//! Node animations: glTF 2.0 `translation`, `rotation`, `scale` and morph target
//! `weights` channels, played back as the glTF 2.0 specification (and its interpolation
//! appendix) defines them, with skins and morph targets applied to the meshes they deform.
//!
//! The loader keeps what it needs to place the scene's instances at any time: the node
//! hierarchy it walked (each node's parent and static transform), which node each
//! [`crate::Instance`] comes from, and the channels. [`crate::Scene::set_time`] and
//! [`crate::Scene::instance_transforms_at`] use it.
//!
//! Interpolation, between keys `k` and `k + 1` with `td = t[k+1] - t[k]` and
//! `s = (T - t[k]) / td`:
//!
//! - [`Interpolation::Step`]: the value of key `k`;
//! - [`Interpolation::Linear`]: `v[k] + s (v[k+1] - v[k])`; rotations use spherical
//!   linear interpolation (slerp) along the shortest path;
//! - [`Interpolation::CubicSpline`]: the cubic Hermite spline
//!   `(2s³ - 3s² + 1) v[k] + td (s³ - 2s² + s) b[k] + (-2s³ + 3s²) v[k+1] + td (s³ - s²) a[k+1]`,
//!   where `a` are the in-tangents and `b` the out-tangents; rotations are normalised
//!   afterwards.
//!
//! Before the first key the first value holds; after the last key the last value holds.

use glam::{DVec4, Mat4, Quat, Vec3, Vec4};

/// How a channel interpolates between its keys (glTF `sampler.interpolation`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Interpolation {
    /// `LINEAR`: linear interpolation; spherical linear interpolation for rotations.
    Linear,
    /// `STEP`: each key's value holds until the next key.
    Step,
    /// `CUBICSPLINE`: cubic Hermite spline; each key has an in-tangent, a value and an
    /// out-tangent (in that order in [`Channel::values`]).
    CubicSpline,
}

impl Interpolation {
    /// The glTF name: `"LINEAR"`, `"STEP"` or `"CUBICSPLINE"`.
    pub fn name(self) -> &'static str {
        match self {
            Interpolation::Linear => "LINEAR",
            Interpolation::Step => "STEP",
            Interpolation::CubicSpline => "CUBICSPLINE",
        }
    }
}

/// The node property a channel drives (glTF `channel.target.path`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Property {
    /// The node's translation (`x, y, z`; `w` unused, zero).
    Translation,
    /// The node's rotation, a unit quaternion (`x, y, z, w`).
    Rotation,
    /// The node's scale (`x, y, z`; `w` unused, zero).
    Scale,
    /// Four of the node's morph target weights: `Weights(c)` drives targets `4c..4c + 4`
    /// (`x, y, z, w`; entries past the mesh's targets are zero). A glTF `weights` channel
    /// becomes one such channel per four targets, each interpolated component by component.
    Weights(u16),
}

impl Property {
    /// The glTF name: `"translation"`, `"rotation"`, `"scale"` or `"weights"`.
    pub fn name(self) -> &'static str {
        match self {
            Property::Translation => "translation",
            Property::Rotation => "rotation",
            Property::Scale => "scale",
            Property::Weights(_) => "weights",
        }
    }
}

/// One animated property of one node: key times, values and how to interpolate them.
///
/// Built (and checked) by [`Channel::new`]; the checks make [`Channel::value_at`] total.
#[derive(Clone, Debug, PartialEq)]
pub struct Channel {
    node: usize,
    property: Property,
    interpolation: Interpolation,
    times: Vec<f32>,
    values: Vec<Vec4>,
}

impl Channel {
    /// A channel driving `property` of node `node` (an index into [`Animation::nodes`]).
    ///
    /// `times` are the key times in seconds: at least one, finite, strictly increasing.
    /// `values` are finite, one per key (three per key for [`Interpolation::CubicSpline`]:
    /// in-tangent, value, out-tangent); translations and scales use `x, y, z` and ignore
    /// `w`. Rotation keys of [`Interpolation::Linear`] and [`Interpolation::Step`] must
    /// not be zero; they are normalised (keys already of unit length within `1e-5` are
    /// kept as they are, bit for bit).
    ///
    /// The error says what is wrong, e.g. `"key time 2 (0.5) is not greater than key
    /// time 1 (0.5)"`.
    pub fn new(
        node: usize,
        property: Property,
        interpolation: Interpolation,
        times: Vec<f32>,
        mut values: Vec<Vec4>,
    ) -> Result<Channel, String> {
        if times.is_empty() {
            return Err("it has no keys (the input accessor is empty)".into());
        }
        if let Some(k) = times.iter().position(|t| !t.is_finite()) {
            return Err(format!("key time {k} is not finite ({})", times[k]));
        }
        if let Some(k) = (1..times.len()).find(|&k| times[k] <= times[k - 1]) {
            return Err(format!(
                "key time {k} ({}) is not greater than key time {} ({}): key times must be strictly increasing",
                times[k],
                k - 1,
                times[k - 1]
            ));
        }
        let per_key = if interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        let want = times.len().saturating_mul(per_key);
        if values.len() != want {
            return Err(format!(
                "the output has {} values but the input has {} keys ({} needs {})",
                values.len(),
                times.len(),
                interpolation.name(),
                if per_key == 3 {
                    format!("3 per key: in-tangent, value, out-tangent, so {want}")
                } else {
                    format!("one per key, so {want}")
                }
            ));
        }
        if matches!(property, Property::Translation | Property::Scale) {
            for v in &mut values {
                v.w = 0.0;
            }
        }
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            return Err(format!("output value {k} is not finite ({})", values[k]));
        }
        if property == Property::Rotation && interpolation != Interpolation::CubicSpline {
            for (k, q) in values.iter_mut().enumerate() {
                let l2 = q.length_squared();
                if (l2 - 1.0).abs() <= 1e-5 {
                    continue;
                }
                let len = l2.sqrt();
                if !(len.is_finite() && len > 1e-6) {
                    return Err(format!(
                        "rotation key {k} ({q}) is not a unit quaternion and cannot be normalised"
                    ));
                }
                *q /= len;
            }
        }
        Ok(Channel {
            node,
            property,
            interpolation,
            times,
            values,
        })
    }

    /// The node it drives: an index into [`Animation::nodes`].
    pub fn node(&self) -> usize {
        self.node
    }

    /// The property it drives.
    pub fn property(&self) -> Property {
        self.property
    }

    /// How it interpolates.
    pub fn interpolation(&self) -> Interpolation {
        self.interpolation
    }

    /// The key times, in seconds (finite, strictly increasing, at least one).
    pub fn times(&self) -> &[f32] {
        &self.times
    }

    /// The output values: one per key, or in-tangent, value, out-tangent per key for
    /// [`Interpolation::CubicSpline`]. Translations and scales have `w = 0`.
    pub fn values(&self) -> &[Vec4] {
        &self.values
    }

    /// The time of the last key.
    pub fn end_time(&self) -> f32 {
        self.times.last().copied().unwrap_or(0.0)
    }

    /// The value of key `k` (not a tangent).
    fn key(&self, k: usize) -> Vec4 {
        match self.interpolation {
            Interpolation::CubicSpline => self.values[3 * k + 1],
            _ => self.values[k],
        }
    }

    /// The property's value at time `t` (seconds): a translation or scale in `x, y, z`
    /// (`w = 0`), a rotation quaternion `x, y, z, w`, or four morph target weights. Before the first key the first
    /// value holds, after the last key the last one; at a key time the key's value is
    /// returned exactly (a [`Interpolation::CubicSpline`] rotation is normalised). A NaN
    /// time is taken as the start.
    pub fn value_at(&self, t: f32) -> Vec4 {
        let n = self.times.len();
        let is_rot = self.property == Property::Rotation;
        let cubic_rot = is_rot && self.interpolation == Interpolation::CubicSpline;
        let finish = |v: Vec4| if cubic_rot { unit_quat(v) } else { v };
        if t.is_nan() || t <= self.times[0] {
            return finish(self.key(0));
        }
        if t >= self.times[n - 1] {
            return finish(self.key(n - 1));
        }
        // times[k] <= t < times[k + 1], k + 1 < n.
        let k = self.times.partition_point(|&x| x <= t) - 1;
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        if t == t0 {
            return finish(self.key(k));
        }
        let td = t1 - t0;
        let s = ((t - t0) / td).clamp(0.0, 1.0);
        match self.interpolation {
            Interpolation::Step => self.key(k),
            Interpolation::Linear if is_rot => slerp(self.key(k), self.key(k + 1), s),
            Interpolation::Linear => self.key(k).lerp(self.key(k + 1), s),
            Interpolation::CubicSpline => {
                let v0 = self.values[3 * k + 1];
                let b0 = self.values[3 * k + 2];
                let a1 = self.values[3 * (k + 1)];
                let v1 = self.values[3 * (k + 1) + 1];
                let (s2, s3) = (s * s, s * s * s);
                let p = v0 * (2.0 * s3 - 3.0 * s2 + 1.0)
                    + b0 * (td * (s3 - 2.0 * s2 + s))
                    + v1 * (-2.0 * s3 + 3.0 * s2)
                    + a1 * (td * (s3 - s2));
                finish(p)
            }
        }
    }
}

/// `q` normalised; the identity when `q` has no direction (a degenerate spline).
fn unit_quat(q: Vec4) -> Vec4 {
    let len = q.length();
    if len.is_finite() && len > 1e-12 {
        q / len
    } else {
        Vec4::W
    }
}

/// Spherical linear interpolation of unit quaternions along the shortest path (the glTF
/// specification's appendix), with the weights computed in `f64`.
fn slerp(a: Vec4, b: Vec4, s: f32) -> Vec4 {
    let (a64, mut b64) = (a.as_dvec4(), b.as_dvec4());
    let mut d = a64.dot(b64);
    if d < 0.0 {
        b64 = -b64;
        d = -d;
    }
    let s = f64::from(s);
    let q: DVec4 = if d > 0.9995 {
        (a64 + (b64 - a64) * s).normalize_or_zero()
    } else {
        let theta0 = d.min(1.0).acos();
        let theta = theta0 * s;
        let (sin_theta, sin_theta0) = (theta.sin(), theta0.sin());
        let s0 = theta.cos() - d * sin_theta / sin_theta0;
        let s1 = sin_theta / sin_theta0;
        a64 * s0 + b64 * s1
    };
    unit_quat(q.as_vec4())
}

/// A node's own transform, relative to its parent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NodeTransform {
    /// A `matrix`: such a node cannot be animated (channels on it are dropped with a
    /// warning).
    Matrix(Mat4),
    /// Translation, rotation and scale, as in the file (missing ones are the identity);
    /// the rotation is normalised when composed. Animated properties replace these.
    Trs {
        /// The static translation.
        translation: Vec3,
        /// The static rotation, as in the file (normalised when composed).
        rotation: Quat,
        /// The static scale.
        scale: Vec3,
    },
}

/// `T * R * S` with the rotation normalised: how the loader composes a node's TRS.
pub(crate) fn compose_trs(translation: Vec3, rotation: Vec4, scale: Vec3) -> Mat4 {
    let len = rotation.length();
    let q = if len.is_finite() && len > 1e-12 {
        Quat::from_vec4(rotation / len)
    } else {
        Quat::IDENTITY
    };
    Mat4::from_scale_rotation_translation(scale, q, translation)
}

/// One node of the loaded scene graph.
#[derive(Clone, Debug, PartialEq)]
pub struct AnimationNode {
    pub(crate) gltf_node: usize,
    pub(crate) parent: Option<usize>,
    pub(crate) local: NodeTransform,
}

impl AnimationNode {
    /// The node's index in the glTF file.
    pub fn gltf_node(&self) -> usize {
        self.gltf_node
    }

    /// Its parent: an index into [`Animation::nodes`], always smaller than its own;
    /// `None` for a root.
    pub fn parent(&self) -> Option<usize> {
        self.parent
    }

    /// Its static transform, relative to its parent.
    pub fn local(&self) -> NodeTransform {
        self.local
    }
}

/// What a scene needs to place its instances at any time: the loaded node hierarchy,
/// the node each instance comes from, the channels, and the global transforms applied
/// after loading ([`crate::Scene::transform`]).
///
/// Every animation of the file plays at once, from time 0; where two channels drive the
/// same property of the same node, the later one (in file order) wins.
#[derive(Clone, Debug, PartialEq)]
pub struct Animation {
    pub(crate) nodes: Vec<AnimationNode>,
    pub(crate) instance_nodes: Vec<usize>,
    pub(crate) channels: Vec<Channel>,
    pub(crate) globals: Vec<Mat4>,
    pub(crate) skins: Vec<Skin>,
    pub(crate) morphs: Vec<Morph>,
}

/// An instance whose mesh has morph targets (glTF `targets`): its own mesh's vertices are
/// `base + Σ weight_i * delta_i` ([`morph_vertex`]), with the weights its node's `weights`
/// channels give at each time (else the node's or the mesh's static `weights`). Morphing
/// comes before skinning, as glTF 2.0 says.
#[derive(Clone, Debug, PartialEq)]
pub struct Morph {
    /// The instance it deforms (its mesh is its own).
    pub(crate) instance: usize,
    /// Its node, an index into [`Animation::nodes`]: the target of its weights channels.
    pub(crate) node: usize,
    /// The static weights, one per target.
    pub(crate) weights: Vec<f32>,
    /// The mesh's positions and normals (normals may be empty) as the file gives them.
    pub(crate) base_positions: Vec<Vec3>,
    pub(crate) base_normals: Vec<Vec3>,
    /// Position deltas, target by target: target `i`'s delta for vertex `v` is at
    /// `i * vertices + v`.
    pub(crate) position_deltas: Vec<Vec3>,
    /// Normal deltas in the same order; empty when no target has normals.
    pub(crate) normal_deltas: Vec<Vec3>,
}

/// One vertex morphed, operation for operation as `shaders/morph.wgsl` does it on the
/// device (`GpuMorph` in bvhtrace-gpu): starting from `base`, each target in order with a
/// weight other than zero adds `delta * weight`, coordinate by coordinate.
pub fn morph_vertex(base: Vec3, deltas: impl IntoIterator<Item = (f32, Vec3)>) -> Vec3 {
    let mut p = base;
    for (w, d) in deltas {
        if w != 0.0 {
            p = Vec3::new(p.x + d.x * w, p.y + d.y * w, p.z + d.z * w);
        }
    }
    p
}

impl Morph {
    /// The instance it deforms.
    pub fn instance(&self) -> usize {
        self.instance
    }

    /// Its number of morph targets.
    pub fn target_count(&self) -> usize {
        self.weights.len()
    }

    /// The static weights, one per target (the node's `weights`, else the mesh's, else 0).
    pub fn static_weights(&self) -> &[f32] {
        &self.weights
    }

    /// The mesh's positions as the file gives them, before any target is applied.
    pub fn base_positions(&self) -> &[Vec3] {
        &self.base_positions
    }

    /// The position deltas, target by target (`target * vertices + vertex`).
    pub fn position_deltas(&self) -> &[Vec3] {
        &self.position_deltas
    }

    /// The morphed positions and normals for `weights` (one per target; missing ones are
    /// 0). Normals are the base normals plus their weighted deltas, normalised (a normal
    /// that vanishes keeps its base).
    pub fn morphed(&self, weights: &[f32]) -> (Vec<Vec3>, Vec<Vec3>) {
        let n = self.base_positions.len();
        let targets = self.target_count();
        let w = |i: usize| weights.get(i).copied().unwrap_or(0.0);
        let morph = |base: Vec3, deltas: &[Vec3], v: usize| {
            morph_vertex(base, (0..targets).map(|i| (w(i), deltas[i * n + v])))
        };
        let positions = (0..n)
            .map(|v| morph(self.base_positions[v], &self.position_deltas, v))
            .collect();
        let normals = if self.normal_deltas.is_empty() {
            self.base_normals.clone()
        } else {
            (0..self.base_normals.len())
                .map(|v| {
                    let base = self.base_normals[v];
                    let m = morph(base, &self.normal_deltas, v).normalize_or_zero();
                    if m == Vec3::ZERO { base } else { m }
                })
                .collect()
        };
        (positions, normals)
    }
}

/// A deformed instance's mesh at one time ([`Animation::deformed_at`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Deformed {
    /// The instance (its mesh is its own).
    pub instance: usize,
    /// Its positions, in the world when it is skinned (the global transform in them),
    /// else in its object space.
    pub positions: Vec<Vec3>,
    /// Its normals, in the same space; empty when the mesh has none.
    pub normals: Vec<Vec3>,
}

/// A skinned instance (glTF skins, linear blend skinning): its own mesh's vertices are
/// placed in the world by joints, `Σ weight * (joint_world * inverse_bind) * bind_position`,
/// and its node's transform is ignored, as glTF 2.0 says.
#[derive(Clone, Debug, PartialEq)]
pub struct Skin {
    /// The instance it places (its mesh is its own).
    pub(crate) instance: usize,
    /// Each joint's node, an index into [`Animation::nodes`].
    pub(crate) joints: Vec<usize>,
    /// Each joint's inverse bind matrix.
    pub(crate) inverse_bind: Vec<Mat4>,
    /// Per vertex: four joints (indices into `joints`) and their weights.
    pub(crate) vertex_joints: Vec<[u16; 4]>,
    pub(crate) vertex_weights: Vec<[f32; 4]>,
    /// The mesh's positions and normals (normals may be empty) as the file gives them.
    pub(crate) bind_positions: Vec<Vec3>,
    pub(crate) bind_normals: Vec<Vec3>,
}

/// One vertex skinned, operation for operation as `shaders/skin.wgsl` does it on the
/// device (`GpuSkin` in bvhtrace-gpu): the blended matrix `Σ w_k M_{j_k}`, element by
/// element, weights in order (zero weights and joints out of range skipped), then each
/// coordinate `((m0 x + m1 y) + m2 z) + m3` over the matrix's columns.
pub fn skin_vertex(matrices: &[Mat4], joints: [u16; 4], weights: [f32; 4], p: Vec3) -> Vec3 {
    let m = blend(matrices, joints, weights);
    let r = |c: usize| ((m[c] * p.x + m[4 + c] * p.y) + m[8 + c] * p.z) + m[12 + c];
    Vec3::new(r(0), r(1), r(2))
}

/// A vertex's blended matrix `Σ w_k M_{j_k}` (columns), element by element, weights in
/// order; zero weights and joints out of range are skipped.
fn blend(matrices: &[Mat4], joints: [u16; 4], weights: [f32; 4]) -> [f32; 16] {
    let mut m = [0f32; 16];
    for k in 0..4 {
        let j = joints[k] as usize;
        if weights[k] != 0.0 && j < matrices.len() {
            let src = matrices[j].to_cols_array();
            for (e, s) in m.iter_mut().zip(src) {
                *e += s * weights[k];
            }
        }
    }
    m
}

impl Skin {
    /// The mesh's positions as the file gives them (the bind pose).
    pub fn bind_positions(&self) -> &[Vec3] {
        &self.bind_positions
    }

    /// Per vertex, four joints (indices into the skin's joints).
    pub fn vertex_joints(&self) -> &[[u16; 4]] {
        &self.vertex_joints
    }

    /// Per vertex, the four joints' weights.
    pub fn vertex_weights(&self) -> &[[f32; 4]] {
        &self.vertex_weights
    }

    /// The instance it places.
    pub fn instance(&self) -> usize {
        self.instance
    }

    /// Number of joints.
    pub fn joint_count(&self) -> usize {
        self.joints.len()
    }

    /// Each joint's skinning matrix (`joint_world * inverse_bind`) for the nodes' world
    /// transforms `world` ([`Animation::node_transforms_at`]), the global transform
    /// `global` applied after.
    pub fn joint_matrices(&self, world: &[Mat4], global: Mat4) -> Vec<Mat4> {
        self.joints
            .iter()
            .zip(&self.inverse_bind)
            .map(|(&j, ibm)| global * world.get(j).copied().unwrap_or(Mat4::IDENTITY) * *ibm)
            .collect()
    }

    /// The skinned positions and normals for `matrices` ([`Skin::joint_matrices`]), from
    /// the bind pose.
    pub fn skinned(&self, matrices: &[Mat4]) -> (Vec<Vec3>, Vec<Vec3>) {
        self.skin(matrices, &self.bind_positions, &self.bind_normals)
    }

    /// `positions` and `normals` (the bind pose, or a morphed one: one per vertex of the
    /// mesh; normals may be empty) skinned with `matrices`.
    pub fn skin(
        &self,
        matrices: &[Mat4],
        positions: &[Vec3],
        normals: &[Vec3],
    ) -> (Vec<Vec3>, Vec<Vec3>) {
        let vertex = |v: usize| (self.vertex_joints[v], self.vertex_weights[v]);
        let positions = (0..positions.len().min(self.vertex_joints.len()))
            .map(|v| {
                let (j, w) = vertex(v);
                skin_vertex(matrices, j, w, positions[v])
            })
            .collect();
        let normals = (0..normals.len().min(self.vertex_joints.len()))
            .map(|v| {
                let (j, w) = vertex(v);
                let m = Mat4::from_cols_array(&blend(matrices, j, w));
                let n = m.inverse().transpose().transform_vector3(normals[v]);
                let n = n.normalize_or_zero();
                if n == Vec3::ZERO { normals[v] } else { n }
            })
            .collect();
        (positions, normals)
    }
}

impl Animation {
    /// The length of the animation in seconds: the latest key time of any channel (at
    /// least 0).
    pub fn duration(&self) -> f32 {
        self.channels
            .iter()
            .map(Channel::end_time)
            .fold(0.0, f32::max)
    }

    /// The nodes of the loaded scene graph, parents before their children.
    pub fn nodes(&self) -> &[AnimationNode] {
        &self.nodes
    }

    /// For each instance of the scene (in [`crate::Scene::instances`] order), its node:
    /// an index into [`Animation::nodes`].
    pub fn instance_nodes(&self) -> &[usize] {
        &self.instance_nodes
    }

    /// The channels, in file order.
    pub fn channels(&self) -> &[Channel] {
        &self.channels
    }

    /// The skinned instances.
    pub fn skins(&self) -> &[Skin] {
        &self.skins
    }

    /// The product of the global transforms applied to the scene after loading (the
    /// identity when none was): world transforms are premultiplied by it.
    pub fn global_transform(&self) -> Mat4 {
        self.globals.iter().fold(Mat4::IDENTITY, |acc, &m| m * acc)
    }

    /// Each node's transform relative to its parent at time `t`.
    fn local_transforms_at(&self, t: f32) -> Vec<Mat4> {
        // Static TRS first, then the channels (later channels win).
        let mut trs: Vec<Option<(Vec3, Vec4, Vec3)>> = self
            .nodes
            .iter()
            .map(|n| match n.local {
                NodeTransform::Matrix(_) => None,
                NodeTransform::Trs {
                    translation,
                    rotation,
                    scale,
                } => Some((translation, Vec4::from(rotation), scale)),
            })
            .collect();
        for c in &self.channels {
            let Some(Some((tr, rot, sc))) = trs.get_mut(c.node) else {
                continue;
            };
            match c.property {
                Property::Translation => *tr = c.value_at(t).truncate(),
                Property::Rotation => *rot = c.value_at(t),
                Property::Scale => *sc = c.value_at(t).truncate(),
                Property::Weights(_) => {}
            }
        }
        self.nodes
            .iter()
            .zip(trs)
            .map(|(n, trs)| match (n.local, trs) {
                (_, Some((tr, rot, sc))) => compose_trs(tr, rot, sc),
                (NodeTransform::Matrix(m), None) => m,
                (NodeTransform::Trs { .. }, None) => Mat4::IDENTITY,
            })
            .collect()
    }

    /// Each node's world transform at time `t` (before the global transform).
    pub fn node_transforms_at(&self, t: f32) -> Vec<Mat4> {
        self.worlds(self.local_transforms_at(t))
    }

    /// Each node's world transform in the file's static pose (no channel applied).
    pub fn static_node_transforms(&self) -> Vec<Mat4> {
        let local = self
            .nodes
            .iter()
            .map(|n| match n.local {
                NodeTransform::Matrix(m) => m,
                NodeTransform::Trs {
                    translation,
                    rotation,
                    scale,
                } => compose_trs(translation, Vec4::from(rotation), scale),
            })
            .collect();
        self.worlds(local)
    }

    /// World transforms from local ones, parents before children.
    fn worlds(&self, local: Vec<Mat4>) -> Vec<Mat4> {
        let mut world = local;
        for i in 0..world.len() {
            if let Some(p) = self.nodes[i].parent.filter(|&p| p < i) {
                world[i] = world[p] * world[i];
            } else {
                world[i] = Mat4::IDENTITY * world[i];
            }
        }
        world
    }

    /// Each instance's object-to-world transform at time `t`, global transform included,
    /// in [`Animation::instance_nodes`] order.
    /// A skinned instance's is the global transform alone: its joints place it.
    pub fn instance_transforms_at(&self, t: f32) -> Vec<Mat4> {
        let world = self.node_transforms_at(t);
        let mut out: Vec<Mat4> = self
            .instance_nodes
            .iter()
            .map(|&n| {
                let w = world.get(n).copied().unwrap_or(Mat4::IDENTITY);
                self.globals.iter().fold(w, |acc, &m| m * acc)
            })
            .collect();
        for s in &self.skins {
            if let Some(m) = out.get_mut(s.instance) {
                *m = Mat4::IDENTITY;
            }
        }
        out
    }

    /// The instances whose meshes morph targets deform.
    pub fn morphs(&self) -> &[Morph] {
        &self.morphs
    }

    /// `morph`'s weights at time `t` (seconds): its static weights, overwritten by its
    /// node's `weights` channels (later channels win). `None` is the static weights.
    pub fn morph_weights_at(&self, morph: &Morph, t: Option<f32>) -> Vec<f32> {
        let mut w = morph.weights.clone();
        let Some(t) = t else {
            return w;
        };
        for c in self.channels.iter().filter(|c| c.node == morph.node) {
            if let Property::Weights(chunk) = c.property {
                let v = c.value_at(t).to_array();
                for (k, x) in v.into_iter().enumerate() {
                    if let Some(slot) = w.get_mut(4 * chunk as usize + k) {
                        *slot = x;
                    }
                }
            }
        }
        w
    }

    /// Each deformed instance's mesh at time `t` (`None`: the static pose, as loaded), in
    /// instance order: morph targets first ([`Morph::morphed`]), then the skin
    /// ([`Skin::skin`]); a skinned mesh's positions are in the world with the global
    /// transform in them.
    pub fn deformed_at(&self, t: Option<f32>) -> Vec<Deformed> {
        type Deforms<'a> = (Option<&'a Morph>, Option<&'a Skin>);
        let mut by_instance: std::collections::BTreeMap<usize, Deforms<'_>> = Default::default();
        for m in &self.morphs {
            by_instance.entry(m.instance).or_default().0 = Some(m);
        }
        for s in &self.skins {
            by_instance.entry(s.instance).or_default().1 = Some(s);
        }
        if by_instance.is_empty() {
            return Vec::new();
        }
        let world = match (t, self.skins.is_empty()) {
            (_, true) => Vec::new(),
            (Some(t), false) => self.node_transforms_at(t),
            (None, false) => self.static_node_transforms(),
        };
        let global = self.global_transform();
        by_instance
            .into_iter()
            .map(|(instance, (morph, skin))| {
                let morphed = morph.map(|m| m.morphed(&self.morph_weights_at(m, t)));
                let matrices = |s: &Skin| s.joint_matrices(&world, global);
                let (positions, normals) = match (skin, morphed) {
                    (Some(s), Some((p, n))) => s.skin(&matrices(s), &p, &n),
                    (Some(s), None) => s.skinned(&matrices(s)),
                    (None, Some(morphed)) => morphed,
                    (None, None) => (Vec::new(), Vec::new()),
                };
                Deformed {
                    instance,
                    positions,
                    normals,
                }
            })
            .collect()
    }
}
