//! The ray-query kernels: the device's own acceleration structure (wgpu's
//! `EXPERIMENTAL_RAY_QUERY`, `VK_KHR_ray_query`) walked by `rayQuery` in WGSL, composed
//! from the same files as our walks (the ray and hit types, the triangle and instance
//! bindings, the entry point) with `bvh_ray_query.wgsl` in place of the walk.
//!
//! | binding (group 0) | what | when |
//! |---|---|---|
//! | 0 | the TLAS (`acceleration_structure`) | always |
//! | 1 | the triangles, `FlatTriangle` in leaf order (the BLAS vertices too) | always |
//! | 9, 17, ... | further pages of the triangles, ranges of the same buffer | a split ([`crate::pages`]) |
//! | 2 | each mesh's first triangle slot, `u32` | two levels |
//! | 4 | the instances, `FlatInstance` | two levels |
//! | 5 | the alpha masks, `MaskTables::words` (`bvh_alpha_masks.wgsl`) | masks |
//!
//! The batch group (rays, hits) is the walks' buffer one ([`crate::RayInput::Buffer`]).
//!
//! With masks, the masked meshes' BLASes are not opaque and the query loop puts each of
//! their candidates to our walks' test (`bvh_alpha_accept`, `bvh_ray_query_masks.wgsl`),
//! at the driver's barycentrics; without, every triangle is forced opaque
//! (`bvh_ray_query_no_masks.wgsl`) and no candidate reaches the loop.

use std::borrow::Cow;

use crate::compose::{BVH_GROUP, join, specialise_entry};
use crate::pages::Pages;
use crate::shaders::{self, Wgsl};
use crate::storage::{BvhStorage, RayInput};

/// `enable wgpu_ray_query;`: WGSL wants enable directives before any declaration.
pub const ENABLE: &str = "enable wgpu_ray_query;\n";

/// The entry point of the ray-query kernel (closest or any hit by the `BVH_ANY_HIT`
/// override, as the walks' entry points).
pub const ENTRY_POINT: &str = "bvh_trace_ray_query_main";

/// The files of the ray-query walk for one mesh or two levels (`instanced`), with or
/// without alpha masks (`masks`: `FlatBvh::masks`), without the `enable` line
/// ([`ENABLE`]), without entry points: the types, the ray's validity, the offset of
/// secondary rays, the triangle, instance and masks bindings and the query itself. The
/// triangles are read through `pages` (only their triangle pages: the device's structure
/// takes the nodes' place).
pub fn files(instanced: bool, masks: bool, pages: Pages) -> Vec<(&'static str, Cow<'static, str>)> {
    let mut out: Vec<(&'static str, Cow<'static, str>)> = Vec::with_capacity(10);
    let mut push = |(name, src): Wgsl| out.push((name, src.into()));
    push(shaders::TYPES);
    push(shaders::RAY);
    push(shaders::SURFACE);
    push(shaders::TEXEL);
    let (name, triangles) = BvhStorage::Buffers.triangles_wgsl();
    out.push((name, pages.specialise(triangles).into()));
    let mut push = |(name, src): Wgsl| out.push((name, src.into()));
    push(match instanced {
        true => shaders::BVH_INSTANCES,
        false => shaders::BVH_NO_INSTANCES,
    });
    // The masks at binding 5, as our walks bind them: binding 5 is free in this group too.
    if masks {
        push(shaders::BVH_ALPHA_MASKS);
        push(shaders::BVH_RAY_QUERY_MASKS);
    } else {
        push(shaders::BVH_RAY_QUERY_NO_MASKS);
    }
    push(shaders::BVH_RAY_QUERY);
    push(match instanced {
        true => shaders::BVH_RAY_QUERY_MESHES,
        false => shaders::BVH_RAY_QUERY_ONE_MESH,
    });
    out
}

/// The kernel that traces a batch with ray queries: [`files`], then `entry.wgsl`, the
/// buffer rays and hits, and one entry point ([`ENTRY_POINT`]). Group 0 is the BVH, group
/// 1 the batch (rays at 0, hits at 1).
pub fn kernel_source(instanced: bool, masks: bool, pages: Pages) -> String {
    let mut parts = files(instanced, masks, pages);
    parts.push((shaders::ENTRY.0, shaders::ENTRY.1.into()));
    let (name, src) = RayInput::Buffer.wgsl();
    parts.push((name, src.into()));
    let call = "bvh_trace_ray_query(bvh_load_ray(i), BVH_ANY_HIT)";
    let entry = specialise_entry(ENTRY_POINT, false, call);
    parts.push((shaders::ENTRY_WALK.0, entry.into()));
    compose(&parts, BVH_GROUP)
}

/// `parts` after the `enable` line, the BVH bindings moved to `@group(bvh_group)`.
pub(crate) fn compose(parts: &[(&'static str, Cow<'static, str>)], bvh_group: u32) -> String {
    join(parts, bvh_group, ENABLE)
}
