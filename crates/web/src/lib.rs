//! bvhtrace in a browser and in Node, as the npm package `bvhtrace`: a [`bvh::Bvh`] built
//! once over a mesh or a glTF scene and traced as often as asked, by the CPU layout's
//! walks compiled to WebAssembly (SIMD128) or by the kernels on the page's WebGPU, through
//! the same engine as every other backend (`Tracer::trace_async`). Built for
//! `wasm32-unknown-unknown` and bound to JavaScript with `wasm-bindgen` (`web/build.sh`,
//! `web/package.sh`); on other targets this crate is empty.
#![warn(missing_docs)]

#[cfg(target_arch = "wasm32")]
pub mod bvh;
#[cfg(target_arch = "wasm32")]
pub mod choice;
#[cfg(target_arch = "wasm32")]
pub mod instanced;
#[cfg(all(target_arch = "wasm32", feature = "one-shot"))]
pub mod oneshot;
