//! A backend that does not run in a browser (ash has no browser, WebGPU no ray queries):
//! in a browser build its module is this one, and opening it is an error naming why.

use std::sync::Arc;

use bvhtrace_engine::TraceError;
use bvhtrace_gpu::GpuContext;

use super::interface::DeviceInterface;
use crate::{Backend, OpenOptions};

/// Why `backend` does not open here.
fn not_in_a_browser(backend: Backend) -> TraceError {
    TraceError::NoAdapter {
        details: format!(
            ": the {backend} backend does not run in a browser (WebGPU has no ray queries, and \
             ash no browser; use wgpu)"
        ),
    }
}

/// The backend `opts` asks for: an error here.
pub(crate) fn open(opts: &OpenOptions) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    Err(not_in_a_browser(opts.backend))
}

/// Ray queries on a device: an error here.
#[allow(dead_code)]
pub(crate) fn on(_: GpuContext) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    Err(not_in_a_browser(Backend::RayQuery))
}
