//! Secondary-ray origins: the hit point from barycentrics and the robust origin offset of
//! Wächter and Binder (Ray Tracing Gems, chapter 6), as the renderer uses them: they live
//! in [`bvhtrace_core::surface`], re-exported here for the cases.

pub use bvhtrace_core::surface::{
    OFFSET_FLOAT_SCALE, OFFSET_INT_SCALE, OFFSET_ORIGIN, geometric_normal, hit_point,
    offset_ray_origin,
};
