//! Vulkan results as [`TraceError`]s, the one error type of every backend: every Vulkan
//! and loader failure comes back as one of those, never as a panic.

use ash::vk;
use bvhtrace_engine::TraceError;

/// Maps a failing Vulkan result, naming what was being done: out of (device or host)
/// memory is [`TraceError::OutOfMemory`], a lost device [`TraceError::DeviceLost`], any
/// other result [`TraceError::Device`] with the result's name.
pub(crate) fn from_vk(during: &'static str, result: vk::Result) -> TraceError {
    match result {
        vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
            TraceError::OutOfMemory {
                during,
                message: format!("{result} ({})", result.as_raw()),
            }
        }
        vk::Result::ERROR_DEVICE_LOST => TraceError::DeviceLost { during },
        _ => TraceError::Device {
            during,
            message: format!("Vulkan returned {result} ({})", result.as_raw()),
        },
    }
}

/// `result.map_err(vkerr("doing x"))`.
pub(crate) fn vkerr(during: &'static str) -> impl Fn(vk::Result) -> TraceError {
    move |r| from_vk(during, r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vulkan_results_map_to_errors() {
        let oom = from_vk("uploading", vk::Result::ERROR_OUT_OF_DEVICE_MEMORY);
        assert!(
            matches!(
                oom,
                TraceError::OutOfMemory {
                    during: "uploading",
                    ..
                }
            ),
            "{oom:?}"
        );
        assert!(
            oom.to_string().contains("out of memory while uploading"),
            "{oom}"
        );
        assert!(matches!(
            from_vk("x", vk::Result::ERROR_OUT_OF_HOST_MEMORY),
            TraceError::OutOfMemory { .. }
        ));
        let lost = from_vk("tracing", vk::Result::ERROR_DEVICE_LOST);
        assert!(matches!(lost, TraceError::DeviceLost { .. }));
        assert!(lost.to_string().contains("lost while tracing"), "{lost}");
        let other = vkerr("creating a buffer")(vk::Result::ERROR_INITIALIZATION_FAILED);
        match &other {
            TraceError::Device { during, message } => {
                assert_eq!(*during, "creating a buffer");
                // The raw result code is named, whatever ash's wording of it.
                assert!(
                    message.contains(&vk::Result::ERROR_INITIALIZATION_FAILED.as_raw().to_string())
                );
            }
            e => panic!("expected Device, got {e:?}"),
        }
    }
}
