//! The one list of backends, by name.

use std::fmt;
use std::str::FromStr;

use bvhtrace_engine::Tracer;

/// Which backend traces: every way to trace is named here, and only here.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Backend {
    /// The best there is: wgpu on the first Vulkan adapter by preference (a discrete GPU,
    /// else an integrated or virtual one, else a CPU driver such as lavapipe), and the CPU
    /// walks when there is no Vulkan adapter at all or the scene exceeds the device's
    /// limits in every storage, layout and walk (the [`crate::Opened::fallback`] says so).
    #[default]
    Auto,
    /// The CPU walks of `bvhtrace_core::traverse` on the current rayon pool.
    Cpu,
    /// The WGSL kernels through wgpu (`bvhtrace-gpu`), BVH in buffers or textures.
    Wgpu,
    /// The same kernels on raw Vulkan through ash (`bvhtrace-vk`), BVH in storage buffers.
    Vulkan,
    /// The device's own acceleration structures walked by its ray queries, through wgpu
    /// (`bvhtrace_gpu::RayQueryBvh`; wgpu's `EXPERIMENTAL_RAY_QUERY`): ray-tracing
    /// hardware where there is some, the driver's software walk on lavapipe. The same
    /// answers as our walks under a stated rule, not bit for bit.
    RayQuery,
}

impl Backend {
    /// Every backend, [`Backend::Auto`] first.
    pub const ALL: [Backend; 5] = [
        Backend::Auto,
        Backend::Cpu,
        Backend::Wgpu,
        Backend::Vulkan,
        Backend::RayQuery,
    ];

    /// The name [`FromStr`] reads and [`fmt::Display`] writes; for the device backends,
    /// what their [`Tracer::backend`] returns.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Cpu => "cpu",
            Backend::Wgpu => "wgpu",
            Backend::Vulkan => "vulkan",
            Backend::RayQuery => bvhtrace_gpu::RAY_QUERY_BACKEND,
        }
    }

    /// The other names [`FromStr`] accepts: `gpu` (the command line's name for wgpu),
    /// `vk`, and `rq` or `ray-queries`.
    pub fn aliases(self) -> &'static [&'static str] {
        match self {
            Backend::Wgpu => &["gpu"],
            Backend::Vulkan => &["vk"],
            Backend::RayQuery => &["rq", "ray-queries"],
            Backend::Auto | Backend::Cpu => &[],
        }
    }

    /// The backend a tracer runs on (`None` for a tracer from outside this workspace).
    pub fn of(tracer: &dyn Tracer) -> Option<Backend> {
        tracer.backend().parse().ok()
    }
}

impl fmt::Display for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A backend name [`Backend`]'s [`FromStr`] does not know.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnknownBackend(pub String);

impl fmt::Display for UnknownBackend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let names: Vec<String> = Backend::ALL
            .iter()
            .flat_map(|b| std::iter::once(b.name()).chain(b.aliases().iter().copied()))
            .map(str::to_string)
            .collect();
        write!(
            f,
            "unknown backend {:?}: expected one of {}",
            self.0,
            names.join(", ")
        )
    }
}

impl std::error::Error for UnknownBackend {}

impl FromStr for Backend {
    type Err = UnknownBackend;

    /// A [`Backend::name`] or one of its [`Backend::aliases`], case-insensitive.
    fn from_str(s: &str) -> Result<Backend, UnknownBackend> {
        let wanted = s.trim().to_ascii_lowercase();
        Backend::ALL
            .into_iter()
            .find(|b| b.name() == wanted || b.aliases().contains(&wanted.as_str()))
            .ok_or_else(|| UnknownBackend(s.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for b in Backend::ALL {
            assert_eq!(b.to_string().parse::<Backend>(), Ok(b));
            for alias in b.aliases() {
                assert_eq!(alias.parse::<Backend>(), Ok(b));
            }
        }
        assert_eq!("GPU".parse::<Backend>(), Ok(Backend::Wgpu));
        assert_eq!(" Vulkan ".parse::<Backend>(), Ok(Backend::Vulkan));
        let err = "metal".parse::<Backend>().expect_err("not a backend");
        let text = err.to_string();
        assert!(
            text.contains("\"metal\"") && text.contains("wgpu, gpu"),
            "{text}"
        );
    }

    #[test]
    fn a_tracer_names_its_backend() {
        let bvh = bvhtrace_core::FlatBvh::build(
            &[[glam::Vec3::ZERO, glam::Vec3::X, glam::Vec3::Y]],
            &bvhtrace_core::BuildOptions::default(),
        )
        .expect("one triangle builds");
        let cpu = bvhtrace_engine::CpuTracer::new(&bvh);
        assert_eq!(Backend::of(&cpu), Some(Backend::Cpu));
    }
}
