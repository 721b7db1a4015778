//! Planning a batch on a device: how many rays per dispatch and per submission the
//! device's limits allow, and how big each resource is. The same plan serves every backend.

use bvhtrace_core::{Counters, Hit, Ray};

use crate::compose::WORKGROUP_SIZE;
use crate::device::DriverTuning;
use crate::error::TraceError;
use crate::storage::{BvhStorage, TEXEL_ROW, texel_rows};

/// The device limits a backend works within: the fields of `wgpu::Limits` or Vulkan's
/// `VkPhysicalDeviceLimits` that matter here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceLimits {
    /// Largest storage buffer binding, bytes.
    pub max_storage_buffer_binding_size: u64,
    /// Largest buffer, bytes.
    pub max_buffer_size: u64,
    /// Most workgroups in one dispatch dimension.
    pub max_compute_workgroups_per_dimension: u32,
    /// Alignment of storage buffer binding offsets, bytes.
    pub min_storage_buffer_offset_alignment: u32,
    /// Largest 2D texture side, texels (bounds the texture storage of
    /// [`crate::BvhStorage::Textures`]).
    pub max_texture_dimension_2d: u32,
    /// Most storage buffers one kernel binds (a tree split into pages binds one per page:
    /// [`crate::pages`]).
    pub max_storage_buffers_per_shader_stage: u32,
}

/// Bytes of one [`Ray`] on the device.
pub const RAY_BYTES: u64 = std::mem::size_of::<Ray>() as u64;
/// Bytes of one [`Hit`] on the device.
pub const HIT_BYTES: u64 = std::mem::size_of::<Hit>() as u64;
/// Bytes of one [`Counters`] on the device.
pub const COUNTERS_BYTES: u64 = std::mem::size_of::<Counters>() as u64;

/// The most rays one dispatch handles (about 4M: 128 MiB of rays). Larger batches are split
/// into several dispatches in one compute pass.
pub const MAX_RAYS_PER_DISPATCH: u64 = 1 << 22;

/// Checks that one storage buffer of `bytes` bytes fits the device's limits.
pub fn check_buffer_size(
    limits: &DeviceLimits,
    buffer: &'static str,
    bytes: u64,
) -> Result<(), TraceError> {
    check_buffer_in(limits, buffer, bytes, None)
}

/// [`check_buffer_size`] for an array of the tree kept in `storage`'s buffers (its error
/// names the storage).
pub fn check_buffer_in(
    limits: &DeviceLimits,
    buffer: &'static str,
    bytes: u64,
    storage: Option<BvhStorage>,
) -> Result<(), TraceError> {
    for (limit, limit_name) in [
        (
            limits.max_storage_buffer_binding_size,
            "max_storage_buffer_binding_size",
        ),
        (limits.max_buffer_size, "max_buffer_size"),
    ] {
        if bytes > limit {
            return Err(TraceError::TooLarge {
                buffer,
                bytes,
                limit,
                limit_name,
                storage,
            });
        }
    }
    Ok(())
}

/// Checks one texel texture of `texels` texels against the device's limits: its rows are
/// [`TEXEL_ROW`] wide, and it has [`texel_rows`] of them.
pub fn check_texels(
    limits: &DeviceLimits,
    what: &'static str,
    texels: u64,
    texel_bytes: u64,
) -> Result<(), TraceError> {
    let max = u64::from(limits.max_texture_dimension_2d);
    if u64::from(TEXEL_ROW) > max || texel_rows(texels) > max {
        return Err(TraceError::TooLarge {
            buffer: what,
            bytes: texels * texel_bytes,
            limit: u64::from(TEXEL_ROW).min(max) * max * texel_bytes,
            limit_name: "texture capacity (max_texture_dimension_2d rows of TEXEL_ROW texels; \
                         BvhStorage::Buffers holds more)",
            storage: Some(BvhStorage::Textures),
        });
    }
    Ok(())
}

/// One dispatch of a batch: rays `first_ray .. first_ray + ray_count` on a
/// `groups_x` x `groups_y` grid of [`WORKGROUP_SIZE`]-invocation workgroups.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dispatch {
    /// First ray of the chunk.
    pub first_ray: u64,
    /// Rays in the chunk.
    pub ray_count: u32,
    /// Workgroups along x.
    pub groups_x: u32,
    /// Workgroups along y (1 unless x would exceed the per-dimension limit).
    pub groups_y: u32,
}

/// Rays per dispatch on a device with these limits: at most [`MAX_RAYS_PER_DISPATCH`], at
/// most what one storage binding holds, a multiple of the workgroup size and of the
/// binding-offset alignment (so every chunk's buffer ranges are aligned).
pub fn rays_per_dispatch(limits: &DeviceLimits) -> u64 {
    let align = u64::from(limits.min_storage_buffer_offset_alignment).max(1);
    let step = u64::from(WORKGROUP_SIZE).max(align);
    let by_binding = limits.max_storage_buffer_binding_size / RAY_BYTES;
    let dim = u64::from(limits.max_compute_workgroups_per_dimension.max(1));
    let by_groups = dim * dim * u64::from(WORKGROUP_SIZE);
    let max = MAX_RAYS_PER_DISPATCH.min(by_binding).min(by_groups);
    (max / step * step).max(step)
}

/// The most rays one submission of a trace carries: as many whole dispatches as one
/// device buffer allows (at least one).
pub fn rays_per_submission(limits: &DeviceLimits) -> u64 {
    let chunk = rays_per_dispatch(limits);
    let by_buffer = limits.max_buffer_size / RAY_BYTES / chunk * chunk;
    by_buffer.max(chunk)
}

/// How a trace of `ray_count` rays goes to a device whose submissions carry at most `most`
/// rays, as `tuning` says: `(rays per submission, submissions in flight at once)`. With
/// more than one in flight ([`DriverTuning::in_flight`]) each carries at most the tuning's
/// `submission_rays` (and at least a workgroup), so that a trace has several to overlap.
pub fn submissions_in_flight(ray_count: u64, most: u64, tuning: &DriverTuning) -> (u64, usize) {
    let per_submit = match tuning.in_flight > 1 {
        true => most.min(tuning.submission_rays.max(u64::from(WORKGROUP_SIZE))),
        false => most,
    };
    let submissions = ray_count.div_ceil(per_submit).max(1);
    let in_flight = submissions.min(u64::from(tuning.in_flight.max(1)));
    (per_submit, in_flight as usize)
}

/// Splits a batch of `ray_count` rays into dispatches (see [`rays_per_dispatch`]).
pub fn plan_dispatches(ray_count: u64, limits: &DeviceLimits) -> Vec<Dispatch> {
    let chunk = rays_per_dispatch(limits);
    let dim = limits.max_compute_workgroups_per_dimension.max(1);
    let mut out = Vec::new();
    let mut first = 0;
    while first < ray_count {
        let n = (ray_count - first).min(chunk);
        let groups = n.div_ceil(u64::from(WORKGROUP_SIZE)) as u32;
        let groups_x = groups.min(dim);
        out.push(Dispatch {
            first_ray: first,
            ray_count: n as u32,
            groups_x,
            groups_y: groups.div_ceil(groups_x),
        });
        first += n;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(binding: u64, dim: u32, align: u32) -> DeviceLimits {
        DeviceLimits {
            max_storage_buffer_binding_size: binding,
            max_buffer_size: 1 << 40,
            max_compute_workgroups_per_dimension: dim,
            min_storage_buffer_offset_alignment: align,
            max_texture_dimension_2d: 8192,
            max_storage_buffers_per_shader_stage: 8,
        }
    }

    fn check(ray_count: u64, l: &DeviceLimits) {
        let plan = plan_dispatches(ray_count, l);
        let chunk = rays_per_dispatch(l);
        let mut next = 0;
        for d in &plan {
            assert_eq!(d.first_ray, next, "{plan:?}");
            assert!(u64::from(d.ray_count) <= chunk);
            // Every chunk starts at an aligned offset in all three buffers.
            for stride in [RAY_BYTES, HIT_BYTES, COUNTERS_BYTES] {
                assert_eq!(
                    d.first_ray * stride % u64::from(l.min_storage_buffer_offset_alignment),
                    0
                );
            }
            assert!(u64::from(d.ray_count) * RAY_BYTES <= l.max_storage_buffer_binding_size);
            assert!(d.groups_x <= l.max_compute_workgroups_per_dimension);
            assert!(d.groups_y <= l.max_compute_workgroups_per_dimension);
            let threads = u64::from(d.groups_x) * u64::from(d.groups_y) * u64::from(WORKGROUP_SIZE);
            assert!(threads >= u64::from(d.ray_count));
            // No whole spare row of workgroups.
            assert!(
                threads - u64::from(d.ray_count)
                    < u64::from(d.groups_x) * u64::from(WORKGROUP_SIZE)
            );
            next += u64::from(d.ray_count);
        }
        assert_eq!(next, ray_count);
    }

    #[test]
    fn dispatch_plans_cover_the_batch_within_limits() {
        let lavapipe = limits(128 << 20, 65_535, 64);
        assert_eq!(rays_per_dispatch(&lavapipe), MAX_RAYS_PER_DISPATCH);
        for n in [
            0,
            1,
            63,
            64,
            65,
            1000,
            MAX_RAYS_PER_DISPATCH,
            MAX_RAYS_PER_DISPATCH + 1,
            3 * MAX_RAYS_PER_DISPATCH + 17,
        ] {
            check(n, &lavapipe);
        }
        // The 4M-ray chunk needs 65,536 workgroups: a 2D grid on this device.
        let plan = plan_dispatches(MAX_RAYS_PER_DISPATCH, &lavapipe);
        assert_eq!((plan[0].groups_x, plan[0].groups_y), (65_535, 2));
        // Small bindings, few workgroups per dimension, large alignment.
        let tight = limits(1 << 16, 7, 256);
        assert_eq!(rays_per_dispatch(&tight), 2048 / 256 * 256);
        for n in [1, 255, 256, 2047, 2048, 2049, 100_000] {
            check(n, &tight);
        }
        assert!(plan_dispatches(0, &tight).is_empty());
    }
}
