//! The ray-query kernels: the device's own acceleration structure (wgpu's
//! `EXPERIMENTAL_RAY_QUERY`, `VK_KHR_ray_query`) walked by `rayQuery` in WGSL, composed
//! from the same files as our walks (the ray and hit types, the triangle and instance
//! bindings, the entry point) with `bvh_ray_query.wgsl` in place of the walk.
//!
//! | binding (group 0) | what | when |
//! |---|---|---|
//! | 0 | the TLAS (`acceleration_structure`) | always |
//! | 1 | the triangles, `FlatTriangle` in leaf order (the BLAS vertices too) | always |
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

use crate::key::{
    BVH_ALPHA_MASKS_WGSL, BVH_INSTANCES_WGSL, BVH_NO_INSTANCES_WGSL, ENTRY_WALK_WGSL,
};
use crate::wgsl::{BvhStorage, SHADER_FILES};

/// `enable wgpu_ray_query;`: WGSL wants enable directives before any declaration.
pub const ENABLE: &str = "enable wgpu_ray_query;\n";

/// `bvh_ray_query.wgsl`: the TLAS binding and `bvh_trace_ray_query(ray, any_hit)`.
const BVH_RAY_QUERY_WGSL: (&str, &str) = (
    "bvh_ray_query.wgsl",
    include_str!("../shaders/bvh_ray_query.wgsl"),
);
/// `bvh_ray_query_meshes.wgsl`: each mesh's first triangle slot (binding 2), two levels.
const BVH_RAY_QUERY_MESHES_WGSL: (&str, &str) = (
    "bvh_ray_query_meshes.wgsl",
    include_str!("../shaders/bvh_ray_query_meshes.wgsl"),
);
/// `bvh_ray_query_one_mesh.wgsl`: the same name for one mesh.
const BVH_RAY_QUERY_ONE_MESH_WGSL: (&str, &str) = (
    "bvh_ray_query_one_mesh.wgsl",
    include_str!("../shaders/bvh_ray_query_one_mesh.wgsl"),
);
/// `bvh_ray_query_masks.wgsl`: candidates put to `bvh_alpha_accept` (after
/// `bvh_alpha_masks.wgsl`), for a masked BVH.
const BVH_RAY_QUERY_MASKS_WGSL: (&str, &str) = (
    "bvh_ray_query_masks.wgsl",
    include_str!("../shaders/bvh_ray_query_masks.wgsl"),
);
/// `bvh_ray_query_no_masks.wgsl`: the same names for a BVH without masks (all opaque).
const BVH_RAY_QUERY_NO_MASKS_WGSL: (&str, &str) = (
    "bvh_ray_query_no_masks.wgsl",
    include_str!("../shaders/bvh_ray_query_no_masks.wgsl"),
);

/// The entry point of the ray-query kernel (closest or any hit by the `BVH_ANY_HIT`
/// override, as the walks' entry points).
pub const ENTRY_POINT: &str = "bvh_trace_ray_query_main";

/// The files of the ray-query walk for one mesh or two levels (`instanced`), with or
/// without alpha masks (`masks`: `FlatBvh::masks`), without the `enable` line
/// ([`ENABLE`]), without entry points: the types, the ray's validity, the offset of
/// secondary rays, the triangle, instance and masks bindings and the query itself.
pub fn files(instanced: bool, masks: bool) -> Vec<(&'static str, Cow<'static, str>)> {
    let shared = |wanted: &str| {
        SHADER_FILES
            .iter()
            .find(|(name, _)| *name == wanted)
            .map(|&(name, src)| (name, Cow::Borrowed(src)))
    };
    let mut out: Vec<(&'static str, Cow<'static, str>)> = Vec::with_capacity(10);
    out.extend(shared("types.wgsl"));
    out.extend(shared("ray.wgsl"));
    out.extend(shared("surface.wgsl"));
    let (name, src) = BvhStorage::Buffers.triangles_wgsl();
    out.push((name, src.into()));
    let mut push = |(name, src): (&'static str, &'static str)| out.push((name, src.into()));
    push(if instanced {
        BVH_INSTANCES_WGSL
    } else {
        BVH_NO_INSTANCES_WGSL
    });
    // The masks at binding 5, as our walks bind them: binding 5 is free in this group too.
    if masks {
        push(BVH_ALPHA_MASKS_WGSL);
        push(BVH_RAY_QUERY_MASKS_WGSL);
    } else {
        push(BVH_RAY_QUERY_NO_MASKS_WGSL);
    }
    push(BVH_RAY_QUERY_WGSL);
    push(if instanced {
        BVH_RAY_QUERY_MESHES_WGSL
    } else {
        BVH_RAY_QUERY_ONE_MESH_WGSL
    });
    out
}

/// The kernel that traces a batch with ray queries: [`files`], then `entry.wgsl`, the
/// buffer rays and hits, and one entry point ([`ENTRY_POINT`]). Group 0 is the BVH, group
/// 1 the batch (rays at 0, hits at 1).
pub fn kernel_source(instanced: bool, masks: bool) -> String {
    let mut parts = files(instanced, masks);
    parts.push(("entry.wgsl", crate::wgsl::ENTRY_WGSL.into()));
    let (name, src) = crate::RayInput::Buffer.wgsl();
    parts.push((name, src.into()));
    parts.push((
        "entry_walk.wgsl",
        ENTRY_WALK_WGSL
            .replace("BVH_ENTRY_POINT", ENTRY_POINT)
            .replace("BVH_STORE", "bvh_store_hits_only")
            .replace(
                "BVH_WALK",
                "bvh_trace_ray_query(bvh_load_ray(i), BVH_ANY_HIT)",
            )
            .into(),
    ));
    compose(&parts, crate::wgsl::BVH_GROUP)
}

/// `parts` after the `enable` line, the BVH bindings moved to `@group(bvh_group)`.
pub(crate) fn compose(parts: &[(&'static str, Cow<'static, str>)], bvh_group: u32) -> String {
    let mut s = String::with_capacity(24 * 1024);
    s.push_str(ENABLE);
    let group = format!("@group({bvh_group})");
    for (name, src) in parts {
        s.push_str("// ---- ");
        s.push_str(name);
        s.push_str(" ----\n");
        if bvh_group != 0 && name.starts_with("bvh_") {
            s.push_str(&src.replace("@group(0)", &group));
        } else {
            s.push_str(src);
        }
        s.push('\n');
    }
    s
}
