//! What the path tracer's test files share: opening the device, or saying why they skip.

use bvhtrace_gpu::{AdapterChoice, GpuContext, GpuError};

/// The first adapter, or `None` (printing SKIP for `what`) when there is none; any other
/// failure to open one fails the test.
pub fn context(what: &str) -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Auto) {
        Ok(ctx) => Some(ctx),
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP {what}: {e}");
            None
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    }
}
