//! Your own WGSL over an upload: the traversal library composed for what the upload holds,
//! and its bind group, checked against it. One mesh or two levels, binary or wide layout,
//! buffers or textures: the shader calls `bvh_trace_closest(ray, lane)` and
//! `bvh_trace_any(ray, lane)` the same way on each.

use bvhtrace_engine::{BvhLibrary, LibraryShape, wgsl_library};

use crate::{BvhBindGroup, GpuBvh, GpuError, Traversal};

impl GpuBvh {
    /// What this upload holds, as a library for `traversal` would be composed for it.
    pub fn library_shape(&self, traversal: Traversal) -> LibraryShape {
        let t = self.tree();
        LibraryShape {
            masks: t.masks,
            ..LibraryShape::new(t.storage, t.instanced, traversal)
        }
    }

    /// The traversal library for your own shader ([`bvhtrace_engine::wgsl_library`]),
    /// composed for this upload (its storage, one mesh or two levels) and `traversal`'s
    /// walk, with the BVH bindings in `@group(group)`. An error when the upload does not
    /// hold what `traversal` reads (the wide layout, the escape links). Bind it with
    /// [`GpuBvh::bind_group_for`].
    pub fn wgsl_library(&self, traversal: Traversal, group: u32) -> Result<BvhLibrary, GpuError> {
        self.bind_group(traversal)?;
        Ok(wgsl_library(self.library_shape(traversal), group))
    }

    /// The BVH bind group `library` reads, with its layout for your pipeline layout. A
    /// library composed for another upload (storage, one mesh or two levels) is
    /// [`GpuError::LibraryMismatch`], naming both: its walks would read bindings this
    /// upload does not bind or miss ones it does, which a device does not always report.
    /// Also an error when the upload lacks what the library's walk reads.
    pub fn bind_group_for(&self, library: &BvhLibrary) -> Result<BvhBindGroup<'_>, GpuError> {
        let wanted = library.shape();
        let holds = self.library_shape(wanted.traversal);
        let shape = |s: &LibraryShape| (s.storage, s.instanced, s.masks);
        if shape(&wanted) != shape(&holds) {
            return Err(GpuError::LibraryMismatch {
                library: wanted.to_string(),
                upload: holds.to_string(),
            });
        }
        if !self.context().supports_precision(wanted.precision) {
            return Err(GpuError::PrecisionUnsupported {
                precision: wanted.precision,
                adapter: self.context().adapter_info().name.clone(),
            });
        }
        self.bind_group(wanted.traversal)
    }
}
