//! Choosing a device, and the measures that only help a CPU driver.

use crate::error::TraceError;
use crate::storage::BvhStorage;
use bvhtrace_core::Traversal;

/// Environment variable front ends read to name the adapter to use: any substring of its
/// name, case-insensitive (for example `llvmpipe` or `nvidia`), passed on as
/// [`AdapterChoice::Named`]. The library itself reads no environment variable.
pub const ADAPTER_ENV: &str = "BVHTRACE_ADAPTER";

/// What kind of device an adapter is, as wgpu and Vulkan both report it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DeviceKind {
    /// A discrete GPU.
    DiscreteGpu,
    /// A GPU sharing the CPU's memory.
    IntegratedGpu,
    /// A GPU behind a virtualisation layer.
    VirtualGpu,
    /// A driver that runs on the CPU (Mesa's lavapipe, SwiftShader).
    Cpu,
    /// Anything else.
    Other,
}

impl DeviceKind {
    /// Preference order when no adapter is named: discrete first, CPU drivers last.
    fn rank(self) -> u32 {
        match self {
            DeviceKind::DiscreteGpu => 0,
            DeviceKind::IntegratedGpu => 1,
            DeviceKind::VirtualGpu => 2,
            DeviceKind::Cpu => 3,
            DeviceKind::Other => 4,
        }
    }
}

/// Which adapter a backend opens.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum AdapterChoice {
    /// The best adapter: a discrete GPU, else an integrated one, else a virtual one, else
    /// a CPU driver (lavapipe), ties broken by enumeration order.
    #[default]
    Auto,
    /// The first adapter whose name contains this substring (case-insensitive); for a
    /// command-line flag or [`ADAPTER_ENV`], which front ends read.
    Named(String),
}

impl AdapterChoice {
    /// `Named(name)` for `Some(name)`, else `Auto`.
    pub fn from_name(name: Option<&str>) -> AdapterChoice {
        name.map_or(AdapterChoice::Auto, |n| AdapterChoice::Named(n.to_string()))
    }

    /// The name substring to look for: `Named`'s, else `None` (the best adapter).
    pub fn wanted_name(&self) -> Option<String> {
        match self {
            AdapterChoice::Named(n) => Some(n.clone()),
            AdapterChoice::Auto => None,
        }
    }

    /// Picks among `adapters` (name and kind, in enumeration order): the index of the
    /// chosen one.
    pub fn pick(&self, adapters: &[(String, DeviceKind)]) -> Result<usize, TraceError> {
        if adapters.is_empty() {
            return Err(TraceError::NoAdapter {
                details: String::new(),
            });
        }
        match self.wanted_name() {
            Some(w) => {
                let lw = w.to_lowercase();
                adapters
                    .iter()
                    .position(|(name, _)| name.to_lowercase().contains(&lw))
                    .ok_or_else(|| TraceError::AdapterNotFound {
                        wanted: w.clone(),
                        available: adapters
                            .iter()
                            .map(|(name, kind)| format!("{name} ({kind:?})"))
                            .collect::<Vec<_>>()
                            .join(", "),
                    })
            }
            None => Ok(adapters
                .iter()
                .enumerate()
                .min_by_key(|(i, (_, kind))| (kind.rank(), *i))
                .map_or(0, |(i, _)| i)),
        }
    }
}

/// The trip budget ([`DriverTuning::trip_limit`]) on CPU drivers: lavapipe ends every
/// loop of an invocation after 65,535 trips in all, counted per batch of 8 lanes over all
/// its loops. A ray's trips (box tests, triangle tests) are at most this budget. The count
/// goes up when a loop goes round again (not on entry), so only when some lane runs its
/// next trip. That trip spends one of the lane's trips (or ends the lane, once): a box test
/// for the inner loop, and for a walk's outer loop or the short stack's restart loop, the
/// first box test of the inner loop they enter; or, for a leaf's triangle loop, a triangle
/// test or the end of the leaf, at most once per entry, which is once per outer trip. So a
/// batch counts at most `8 * budget + 8` for the first kind and `8 * budget + 1` for leaf
/// ends: `16 * 3,800 + 9 = 60,809`.
pub const CPU_DRIVER_TRIP_LIMIT: u32 = 3_800;

/// The most threads [`DriverTuning::dispatch_threads`] may name (lavapipe's own cap is
/// lower).
pub const MAX_DISPATCH_THREADS: u32 = 64;

/// What a backend takes per kind of device: the storage and the walk measured fastest
/// there, and the measures that only help a driver that runs on the CPU (Mesa's lavapipe:
/// threads, the trip budget), kept out of the rest of the API. A backend picks
/// [`DriverTuning::for_device`] for its adapter; pass your own to override it
/// (`bvhtrace tune` times the choices on a device). Every setting gives the same hits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DriverTuning {
    /// Where the convenience trace keeps the BVH (both layouts) and the rays: textures on
    /// CPU drivers (a texel fetch is one vector gather there, a buffer load one loop over
    /// the lanes per 32-bit word: the binary walks about 5x faster on Mesa 22's lavapipe,
    /// 1.7-1.8x on Mesa 25's, whose buffer loads are three times faster), buffers
    /// elsewhere. A device without enough storage-texture bindings falls
    /// back to buffers.
    pub storage: BvhStorage,
    /// The worker threads a CPU driver splits each dispatch among (`DISPATCH_THREADS`): the
    /// entry points deal ray blocks out to them in turn, so that each thread gets a share
    /// of every part of a frame. 1 on GPUs, which hand out workgroups as they go.
    pub dispatch_threads: u32,
    /// The kernels' loop-trip budget per ray (`TRIP_LIMIT`), `u32::MAX` for none. A CPU
    /// driver ends any invocation that loops too long; a ray that spends the budget comes
    /// back as [`bvhtrace_core::INCOMPLETE`] and is finished on the CPU, for which the
    /// upload keeps a host copy of the tree.
    pub trip_limit: u32,
    /// The walk a trace takes when none is asked for (`Tracer::default_traversal`, the
    /// front door's first choice), the fastest measured on devices of this kind: the full
    /// stack on a GPU (1.5x the stackless walk on an NVIDIA H200, the first discrete GPU
    /// measured: docs/benchmarks.md), the stackless walk on a CPU driver. A device no
    /// figure covers takes the GPU's.
    pub walk: Traversal,
    /// Submissions of one trace in flight at once, each on scratch of its own: with 2, a
    /// batch's rays are written and the last one's hits copied out while the device walks
    /// (double buffering). 1 on a CPU driver, whose device is the same cores the copies
    /// would take. The ash backend waits for each submission: 1 there whatever is set.
    /// The ray-query tracer keeps its buffers between traces only with more than 1 (on a
    /// CPU driver, buffers made per trace left the other uploads faster: docs/gpu-wall.md).
    pub in_flight: u32,
    /// The most rays one submission of a trace carries when `in_flight` is above 1 (so
    /// that a trace has several to overlap), within the device's buffer limit either way.
    pub submission_rays: u64,
}

impl DriverTuning {
    /// For a GPU: buffers, no interleave, no trip budget, no host copy.
    pub const GPU: DriverTuning = DriverTuning {
        storage: BvhStorage::Buffers,
        dispatch_threads: 1,
        trip_limit: u32::MAX,
        walk: Traversal::FullStack,
        in_flight: 2,
        submission_rays: 1 << 18,
    };

    /// For a CPU driver running `threads` worker threads: textures, the dispatch dealt
    /// out to them, and the trip budget.
    pub fn cpu_driver(threads: u32) -> DriverTuning {
        DriverTuning {
            storage: BvhStorage::Textures,
            dispatch_threads: threads.clamp(1, MAX_DISPATCH_THREADS),
            trip_limit: CPU_DRIVER_TRIP_LIMIT,
            walk: Traversal::Stackless,
            in_flight: 1,
            submission_rays: u64::MAX,
        }
    }

    /// What a backend picks for an adapter of this kind: [`DriverTuning::cpu_driver`] with
    /// one thread per CPU (lavapipe's default) for CPU drivers, [`DriverTuning::GPU`]
    /// otherwise.
    pub fn for_device(kind: DeviceKind) -> DriverTuning {
        if kind == DeviceKind::Cpu {
            let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
            DriverTuning::cpu_driver(u32::try_from(cpus).unwrap_or(MAX_DISPATCH_THREADS))
        } else {
            DriverTuning::GPU
        }
    }

    /// True when rays may come back [`bvhtrace_core::INCOMPLETE`] and the upload keeps a
    /// host copy of the tree to finish them.
    pub fn finishes_on_cpu(&self) -> bool {
        self.trip_limit != u32::MAX
    }

    /// The override constants a pipeline gets from this tuning.
    pub fn constants(&self) -> [(&'static str, f64); 2] {
        [
            ("BVH_TRIP_LIMIT", f64::from(self.trip_limit)),
            ("BVH_DISPATCH_THREADS", f64::from(self.dispatch_threads)),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adapters_are_ranked_and_named() {
        let list = [
            (
                "llvmpipe (LLVM 15.0.6, 256 bits)".to_string(),
                DeviceKind::Cpu,
            ),
            (
                "Intel(R) UHD Graphics".to_string(),
                DeviceKind::IntegratedGpu,
            ),
            (
                "NVIDIA GeForce RTX 4090".to_string(),
                DeviceKind::DiscreteGpu,
            ),
        ];
        let named = |n: &str| AdapterChoice::Named(n.into());
        // Auto reads the environment; name the best one explicitly instead.
        assert_eq!(named("rtx").pick(&list).ok(), Some(2));
        assert_eq!(named("LLVMPIPE").pick(&list).ok(), Some(0));
        assert_eq!(named("uhd").pick(&list).ok(), Some(1));
        match named("radeon").pick(&list) {
            Err(TraceError::AdapterNotFound { wanted, available }) => {
                assert_eq!(wanted, "radeon");
                assert!(available.contains("llvmpipe") && available.contains("RTX 4090"));
            }
            other => panic!("{other:?}"),
        }
        let err = named("x").pick(&[]).expect_err("no adapter");
        assert!(err.to_string().contains("mesa-vulkan-drivers"), "{err}");
        // The environment plays no part: `Auto` is the best adapter.
        assert_eq!(AdapterChoice::Auto.pick(&list).ok(), Some(2));
        assert_eq!(AdapterChoice::Auto.pick(&list[..2]).ok(), Some(1));
        assert_eq!(AdapterChoice::Auto.pick(&list[..1]).ok(), Some(0));
    }

    #[test]
    fn cpu_drivers_get_the_cpu_measures() {
        assert_eq!(
            DriverTuning::for_device(DeviceKind::DiscreteGpu),
            DriverTuning::GPU
        );
        let cpu = DriverTuning::for_device(DeviceKind::Cpu);
        assert_eq!(cpu.storage, BvhStorage::Textures);
        assert!(cpu.finishes_on_cpu() && !DriverTuning::GPU.finishes_on_cpu());
        assert!((1..=MAX_DISPATCH_THREADS).contains(&cpu.dispatch_threads));
        assert_eq!(DriverTuning::cpu_driver(0).dispatch_threads, 1);
        assert_eq!(
            DriverTuning::cpu_driver(100_000).dispatch_threads,
            MAX_DISPATCH_THREADS
        );
    }
}
