//! Turning hits into pixels, and the secondary rays some modes need: the shading shared
//! with the viewer and the examples (`bvhtrace_shade`), under the name the commands use.

pub use bvhtrace_shade::*;
