//! Your own WGSL over an upload: the traversal library composed for what the upload holds,
//! and its bind group, checked against it. One mesh or two levels, binary or wide layout,
//! buffers or textures: the shader calls `bvh_trace_closest(ray, lane)` and
//! `bvh_trace_any(ray, lane)` the same way on each.

use bvhtrace_engine::{BvhLibrary, LibraryShape, wgsl_library};

use crate::{BvhBindGroup, GpuBvh, GpuContext, GpuError, Traversal};

impl GpuBvh {
    /// What this upload holds, as a library for `traversal` would be composed for it.
    pub fn library_shape(&self, traversal: Traversal) -> LibraryShape {
        let t = self.tree();
        LibraryShape {
            masks: t.masks,
            pages: t.layout().pages_for(traversal),
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
        let shape = |s: &LibraryShape| (s.storage, s.instanced, s.masks, s.pages);
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

/// Your source after the library's, and the lines before yours.
fn composed(library: &BvhLibrary, source: &str) -> (String, u32) {
    let prefix = format!("{}\n", library.source());
    let lines = prefix.matches('\n').count() as u32;
    (prefix + source, lines)
}

/// The first error of `info` as [`GpuError::Shader`], its line counted in your source
/// (`before` lines precede it); the compiler's own report is cut to its first line, whose
/// line numbers (a native compiler's snippet counts the library's lines) would mislead.
fn shader_error(label: &str, info: &wgpu::CompilationInfo, before: u32) -> Option<GpuError> {
    let m =
        (info.messages.iter()).find(|m| m.message_type == wgpu::CompilationMessageType::Error)?;
    let first = m
        .message
        .lines()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("");
    // wgpu's own heading (`Shader 'label' parsing error: `) repeats the label.
    let first = (first.trim().strip_prefix("Shader "))
        .and_then(|r| r.split_once(": ").map(|(_, m)| m))
        .unwrap_or(first);
    let message = first.trim().trim_start_matches("error:").trim().to_string();
    let (line, column) = match m.location {
        Some(l) if l.line_number > before => (Some(l.line_number - before), Some(l.line_position)),
        Some(_) => (Some(0), None),
        None => (None, None),
    };
    Some(GpuError::Shader {
        label: label.to_string(),
        line,
        column,
        message,
    })
}

impl GpuContext {
    /// Compiles your shader `source` after `library`'s WGSL (the library first, then your
    /// code, as one module labelled `label`). A shader that does not compile is
    /// [`GpuError::Shader`], its line and column counted in `source` itself, never wgpu's
    /// panic. Blocks until the device answers: in a browser use
    /// [`GpuContext::shader_module_async`].
    pub fn shader_module(
        &self,
        library: &BvhLibrary,
        source: &str,
        label: &str,
    ) -> Result<wgpu::ShaderModule, GpuError> {
        if cfg!(target_arch = "wasm32") {
            return Err(GpuError::Device {
                during: "compiling a shader",
                message: "a browser cannot wait for its GPU: use shader_module_async".into(),
            });
        }
        pollster::block_on(self.shader_module_async(library, source, label))
    }

    /// [`GpuContext::shader_module`] as a future: what a page awaits (the browser's
    /// compiler answers on its event loop).
    pub async fn shader_module_async(
        &self,
        library: &BvhLibrary,
        source: &str,
        label: &str,
    ) -> Result<wgpu::ShaderModule, GpuError> {
        let (text, before) = composed(library, source);
        let device = self.device();
        // The scope takes the validation error wgpu would otherwise hand to its panicking
        // default handler.
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(text.into()),
        });
        let info = module.get_compilation_info().await;
        let scoped = scope.pop().await;
        if let Some(e) = shader_error(label, &info, before) {
            return Err(e);
        }
        match scoped {
            Some(e) => Err(GpuError::Shader {
                label: label.to_string(),
                line: None,
                column: None,
                message: e.to_string(),
            }),
            None => Ok(module),
        }
    }
}
