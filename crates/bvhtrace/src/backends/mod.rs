//! One module per backend, each behind the one object-safe [`DeviceInterface`] (in
//! [`interface`]): the rest of the front door knows a backend only by its [`Backend`] name
//! and this trait. A new backend is a crate, one module here, one [`Backend`] variant and
//! its row, and one arm of [`open`].

use bvhtrace_engine::TraceError;

use crate::{Backend, OpenOptions};
use interface::OpenedDevice;

mod auto;
pub(crate) mod cpu;
pub(crate) mod interface;
pub(crate) mod mock;
#[cfg(not(target_arch = "wasm32"))]
pub(crate) mod ray_query;
#[cfg(target_arch = "wasm32")]
#[path = "in_no_browser.rs"]
pub(crate) mod ray_query;
#[cfg(not(target_arch = "wasm32"))]
pub(crate) mod vulkan;
#[cfg(target_arch = "wasm32")]
#[path = "in_no_browser.rs"]
pub(crate) mod vulkan;
pub(crate) mod wgpu;

#[cfg(doc)]
use interface::DeviceInterface;

/// Opens the backend `opts` asks for on its adapter.
pub(crate) fn open(opts: &OpenOptions) -> Result<OpenedDevice, TraceError> {
    match opts.backend {
        Backend::Auto => auto::open(opts),
        Backend::Cpu => Ok(OpenedDevice::plain(cpu::device())),
        Backend::Wgpu => wgpu::open(opts).map(OpenedDevice::plain),
        Backend::Vulkan => vulkan::open(opts).map(OpenedDevice::plain),
        Backend::RayQuery => ray_query::open(opts).map(OpenedDevice::plain),
        Backend::Mock => mock::open(opts).map(OpenedDevice::plain),
    }
}
