//! Every way to trace, in one table: its name, the other names it is known by, and what
//! its answers promise.

use std::fmt;
use std::str::FromStr;

use bvhtrace_engine::Tracer;

/// Which backend traces: every way to trace is named here, and only here.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Backend {
    /// The best there is: wgpu on the first Vulkan adapter by preference (a discrete GPU,
    /// else an integrated or virtual one, else a CPU driver such as lavapipe), with the
    /// device's ray queries where it has them in hardware, and the CPU walks when there is
    /// no Vulkan adapter at all or the scene exceeds the device's limits in every storage,
    /// layout and walk (the [`crate::Opened::fallback`] says so).
    #[default]
    Auto,
    /// The CPU walks (the CPU layout's SIMD walks for the full stack) on the current rayon
    /// pool.
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
    /// A test backend: the engine over a device of bytes whose kernels are the CPU twins
    /// (`bvhtrace-mock`), for testing a front end without a GPU. Not fast.
    Mock,
}

/// What answers a backend's rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Kernels {
    /// The CPU walks, on the host.
    Cpu,
    /// Our WGSL walks on a device, each the twin of a CPU walk: where a CPU driver's trip
    /// budget or the wide walk's stack makes them give a ray up, the host finishes it.
    Wgsl,
    /// The CPU walks standing in for a device's kernels over the arrays uploaded to it
    /// (a test backend): they give no ray up.
    CpuTwins,
    /// The device's own ray queries: the driver's walk and triangle test.
    Driver,
}

/// One row of [`TABLE`].
struct Row {
    backend: Backend,
    name: &'static str,
    aliases: &'static [&'static str],
    /// What answers its rays.
    kernels: Kernels,
    /// What it is, for a command line's help.
    about: &'static str,
}

/// The backends, [`Backend::Auto`] first.
const TABLE: [Row; 6] = [
    Row {
        backend: Backend::Auto,
        name: "auto",
        aliases: &[],
        kernels: Kernels::Wgsl,
        about: "the best device there is (its ray queries in hardware, else our walks), \
                else the CPU",
    },
    Row {
        backend: Backend::Cpu,
        name: "cpu",
        aliases: &[],
        kernels: Kernels::Cpu,
        about: "the CPU walks",
    },
    Row {
        backend: Backend::Wgpu,
        name: "wgpu",
        aliases: &["gpu"],
        kernels: Kernels::Wgsl,
        about: "our WGSL walks through wgpu",
    },
    Row {
        backend: Backend::Vulkan,
        name: "vulkan",
        aliases: &["vk", "ash"],
        kernels: Kernels::Wgsl,
        about: "the same walks on raw Vulkan through ash",
    },
    Row {
        backend: Backend::RayQuery,
        name: bvhtrace_gpu::RAY_QUERY_BACKEND,
        aliases: &["rq", "ray-queries"],
        kernels: Kernels::Driver,
        about: "the device's own ray queries",
    },
    Row {
        backend: Backend::Mock,
        name: bvhtrace_mock::MOCK_BACKEND,
        aliases: &[],
        kernels: Kernels::CpuTwins,
        about: "a test device: the engine over bytes, the CPU twins for kernels",
    },
];

impl Backend {
    /// Every backend, [`Backend::Auto`] first.
    pub const ALL: [Backend; TABLE.len()] = {
        let mut all = [Backend::Auto; TABLE.len()];
        let mut i = 0;
        while i < TABLE.len() {
            all[i] = TABLE[i].backend;
            i += 1;
        }
        all
    };

    fn row(self) -> &'static Row {
        let i = Backend::ALL.iter().position(|&b| b == self).unwrap_or(0);
        &TABLE[i]
    }

    /// The name [`FromStr`] reads and [`fmt::Display`] writes; for the device backends,
    /// what their [`Tracer::backend`] returns.
    pub fn name(self) -> &'static str {
        self.row().name
    }

    /// The other names [`FromStr`] accepts (`gpu` for wgpu, `vk` for Vulkan, ...).
    pub fn aliases(self) -> &'static [&'static str] {
        self.row().aliases
    }

    /// What the backend is, in a few words.
    pub fn about(self) -> &'static str {
        self.row().about
    }

    /// What answers its rays ([`Backend::Auto`]: what it opens where there is a device).
    pub fn kernels(self) -> Kernels {
        self.row().kernels
    }

    /// True when its answers equal the CPU twins' bit for bit where the device computes
    /// f32 as the CPU does (our walks); false for the device's own ray queries, which
    /// answer under a stated rule.
    pub fn bit_for_bit(self) -> bool {
        self.kernels() != Kernels::Driver
    }

    /// The backend a tracer runs on (`None` for a tracer from outside this workspace).
    pub fn of(tracer: &dyn Tracer) -> Option<Backend> {
        tracer.backend().parse().ok()
    }

    /// Every name and what it is, one `name (aliases): about` per line, for a help text.
    pub fn help() -> String {
        let line = |b: Backend| {
            let aliases = match b.aliases() {
                [] => String::new(),
                a => format!(" ({})", a.join(", ")),
            };
            format!("{}{aliases}: {}", b.name(), b.about())
        };
        Backend::ALL.map(line).join("\n")
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
        let names: Vec<&str> = Backend::ALL
            .iter()
            .flat_map(|b| std::iter::once(b.name()).chain(b.aliases().iter().copied()))
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
        let help = Backend::help();
        assert_eq!(help.lines().count(), Backend::ALL.len(), "{help}");
        assert!(!Backend::RayQuery.bit_for_bit() && Backend::Vulkan.bit_for_bit());
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
