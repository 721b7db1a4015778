//! Four f32 lanes, portable or SSE ([`Lanes`]), and eight ([`Wide`]: two of four, or one
//! AVX register): the few operations the box and triangle tests use, each with the exact
//! IEEE semantics of the scalar code they replace.
//!
//! `min` and `max` are the scalar tests' `fmin`/`fmax` (`if a < b { a } else { b }`),
//! which is what SSE's `minps`/`maxps` (and AVX's `vminps`/`vmaxps`) compute lane by lane (the second operand when
//! either is NaN or the two are equal), so NaN and signed zeros flow through the SIMD
//! tests exactly as through the scalar ones. No operation is fused: Rust never contracts
//! `a * b + c`, and nothing here asks for an FMA.
//!
//! A mask is a lane pattern of all ones (true) or all zeros (false), as SSE compares
//! produce; [`Lanes::bits`] packs the lanes' sign bits (lane `i` in bit `i`).

/// Four f32 lanes and the operations the tests need.
pub(crate) trait Lanes: Copy {
    /// All lanes `x`.
    fn splat(x: f32) -> Self;
    /// The four values of `a`.
    fn load(a: &[f32; 4]) -> Self;
    /// The four values.
    fn store(self) -> [f32; 4];
    /// `self + o` per lane.
    fn add(self, o: Self) -> Self;
    /// `self - o` per lane.
    fn sub(self, o: Self) -> Self;
    /// `self * o` per lane.
    fn mul(self, o: Self) -> Self;
    /// `self / o` per lane (correctly rounded, not a reciprocal estimate).
    fn div(self, o: Self) -> Self;
    /// `if self < o { self } else { o }` per lane.
    fn min(self, o: Self) -> Self;
    /// `if self > o { self } else { o }` per lane.
    fn max(self, o: Self) -> Self;
    /// `|self|` per lane (the sign bit cleared).
    fn abs(self) -> Self;
    /// `-self` per lane (the sign bit flipped).
    fn neg(self) -> Self;
    /// Mask of `self < o`.
    fn lt(self, o: Self) -> Self;
    /// Mask of `self <= o`.
    fn le(self, o: Self) -> Self;
    /// Mask of `self > o`.
    fn gt(self, o: Self) -> Self;
    /// Mask of `self >= o`.
    fn ge(self, o: Self) -> Self;
    /// Mask of `self == o`.
    fn eq(self, o: Self) -> Self;
    /// Bitwise and.
    fn and(self, o: Self) -> Self;
    /// Bitwise or.
    fn or(self, o: Self) -> Self;
    /// `mask ? a : b` per lane, `self` the mask.
    fn select(self, a: Self, b: Self) -> Self;
    /// Lane `i`'s sign bit in bit `i`.
    fn bits(self) -> u32;
}

/// The portable lanes: plain f32 operations, one lane at a time.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Portable([f32; 4]);

#[inline(always)]
fn mask(b: bool) -> f32 {
    f32::from_bits(if b { u32::MAX } else { 0 })
}

impl Portable {
    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> Self {
        Portable(self.0.map(f))
    }
    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        Portable(std::array::from_fn(|i| f(self.0[i], o.0[i])))
    }
    #[inline(always)]
    fn zip_bits(self, o: Self, f: impl Fn(u32, u32) -> u32) -> Self {
        self.zip(o, |a, b| f32::from_bits(f(a.to_bits(), b.to_bits())))
    }
}

impl Lanes for Portable {
    #[inline(always)]
    fn splat(x: f32) -> Self {
        Portable([x; 4])
    }
    #[inline(always)]
    fn load(a: &[f32; 4]) -> Self {
        Portable(*a)
    }
    #[inline(always)]
    fn store(self) -> [f32; 4] {
        self.0
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip(o, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip(o, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.zip(o, |a, b| a * b)
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self.zip(o, |a, b| a / b)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        self.zip(o, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.zip(o, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn abs(self) -> Self {
        self.map(|a| f32::from_bits(a.to_bits() & 0x7fff_ffff))
    }
    #[inline(always)]
    fn neg(self) -> Self {
        self.map(|a| -a)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> Self {
        self.zip(o, |a, b| mask(a < b))
    }
    #[inline(always)]
    fn le(self, o: Self) -> Self {
        self.zip(o, |a, b| mask(a <= b))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> Self {
        self.zip(o, |a, b| mask(a > b))
    }
    #[inline(always)]
    fn ge(self, o: Self) -> Self {
        self.zip(o, |a, b| mask(a >= b))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> Self {
        self.zip(o, |a, b| mask(a == b))
    }
    #[inline(always)]
    fn and(self, o: Self) -> Self {
        self.zip_bits(o, |a, b| a & b)
    }
    #[inline(always)]
    fn or(self, o: Self) -> Self {
        self.zip_bits(o, |a, b| a | b)
    }
    #[inline(always)]
    fn select(self, a: Self, b: Self) -> Self {
        Portable(std::array::from_fn(|i| {
            if self.0[i].to_bits() >> 31 != 0 {
                a.0[i]
            } else {
                b.0[i]
            }
        }))
    }
    #[inline(always)]
    fn bits(self) -> u32 {
        (0..4).fold(0, |m, i| m | ((self.0[i].to_bits() >> 31) << i))
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use sse::Sse;

/// SSE2 lanes: part of every x86-64 CPU, so no detection is needed to use them.
#[cfg(target_arch = "x86_64")]
mod sse {
    use std::arch::x86_64::*;

    use super::Lanes;

    /// Four lanes in an SSE register.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Sse(__m128);

    impl Lanes for Sse {
        #[inline(always)]
        fn splat(x: f32) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_set1_ps(x)) }
        }
        #[inline(always)]
        fn load(a: &[f32; 4]) -> Self {
            // SAFETY: `a` is four readable f32s; the load is unaligned.
            Sse(unsafe { _mm_loadu_ps(a.as_ptr()) })
        }
        #[inline(always)]
        fn store(self) -> [f32; 4] {
            let mut out = [0.0f32; 4];
            // SAFETY: `out` is four writable f32s; the store is unaligned.
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) };
            out
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_div_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn abs(self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe {
                Sse(_mm_and_ps(
                    self.0,
                    _mm_castsi128_ps(_mm_set1_epi32(0x7fff_ffff)),
                ))
            }
        }
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_xor_ps(self.0, _mm_set1_ps(-0.0))) }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_cmplt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_cmple_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_cmpgt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_cmpge_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn eq(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_cmpeq_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn and(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_and_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn or(self, o: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { Sse(_mm_or_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn select(self, a: Self, b: Self) -> Self {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe {
                Sse(_mm_or_ps(
                    _mm_and_ps(self.0, a.0),
                    _mm_andnot_ps(self.0, b.0),
                ))
            }
        }
        #[inline(always)]
        fn bits(self) -> u32 {
            // SAFETY: SSE and SSE2 are part of every x86-64 CPU.
            unsafe { _mm_movemask_ps(self.0) as u32 }
        }
    }
}

#[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
pub(crate) use simd128::Simd128;

/// WebAssembly SIMD lanes (`-C target-feature=+simd128`, which every browser since 2021
/// and Node 16 runs): the same answers as the portable lanes, bit for bit.
#[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
mod simd128 {
    use std::arch::wasm32::*;

    use super::Lanes;

    /// Four lanes in a `v128`.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Simd128(v128);

    impl Lanes for Simd128 {
        #[inline(always)]
        fn splat(x: f32) -> Self {
            Simd128(f32x4_splat(x))
        }
        #[inline(always)]
        fn load(a: &[f32; 4]) -> Self {
            // SAFETY: `a` is 16 readable bytes; WebAssembly loads need no alignment.
            Simd128(unsafe { v128_load(a.as_ptr().cast::<v128>()) })
        }
        #[inline(always)]
        fn store(self) -> [f32; 4] {
            let mut out = [0.0f32; 4];
            // SAFETY: `out` is 16 writable bytes; WebAssembly stores need no alignment.
            unsafe { v128_store(out.as_mut_ptr().cast::<v128>(), self.0) };
            out
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            Simd128(f32x4_add(self.0, o.0))
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            Simd128(f32x4_sub(self.0, o.0))
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            Simd128(f32x4_mul(self.0, o.0))
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            Simd128(f32x4_div(self.0, o.0))
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // `pmin(a, b)` is `b < a ? b : a`, the scalar `if self < o { self } else { o }`
            // (`min` would propagate NaN and order the zeros: not the scalar test).
            Simd128(f32x4_pmin(o.0, self.0))
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            // `pmax(a, b)` is `a < b ? b : a`: `if self > o { self } else { o }`.
            Simd128(f32x4_pmax(o.0, self.0))
        }
        #[inline(always)]
        fn abs(self) -> Self {
            Simd128(f32x4_abs(self.0))
        }
        #[inline(always)]
        fn neg(self) -> Self {
            Simd128(f32x4_neg(self.0))
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self {
            Simd128(f32x4_lt(self.0, o.0))
        }
        #[inline(always)]
        fn le(self, o: Self) -> Self {
            Simd128(f32x4_le(self.0, o.0))
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self {
            Simd128(f32x4_gt(self.0, o.0))
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Self {
            Simd128(f32x4_ge(self.0, o.0))
        }
        #[inline(always)]
        fn eq(self, o: Self) -> Self {
            Simd128(f32x4_eq(self.0, o.0))
        }
        #[inline(always)]
        fn and(self, o: Self) -> Self {
            Simd128(v128_and(self.0, o.0))
        }
        #[inline(always)]
        fn or(self, o: Self) -> Self {
            Simd128(v128_or(self.0, o.0))
        }
        #[inline(always)]
        fn select(self, a: Self, b: Self) -> Self {
            // Masks are whole lanes, so the bitwise select is the lane select.
            Simd128(v128_bitselect(a.0, b.0, self.0))
        }
        #[inline(always)]
        fn bits(self) -> u32 {
            u32::from(i32x4_bitmask(self.0))
        }
    }
}

/// Eight f32 lanes for the box tests of an 8-wide node: the operations [`Lanes`] has,
/// with the same semantics lane by lane (masks as all-ones lanes, [`Wide::bits`] lane `i`
/// in bit `i`).
pub(crate) trait Wide: Copy {
    /// All lanes `x`.
    fn splat(x: f32) -> Self;
    /// The eight values of `a`.
    fn load(a: &[f32; 8]) -> Self;
    /// The eight values.
    fn store(self) -> [f32; 8];
    /// `self + o` per lane.
    fn add(self, o: Self) -> Self;
    /// `self - o` per lane.
    fn sub(self, o: Self) -> Self;
    /// `self * o` per lane.
    fn mul(self, o: Self) -> Self;
    /// `if self < o { self } else { o }` per lane.
    fn min(self, o: Self) -> Self;
    /// `if self > o { self } else { o }` per lane.
    fn max(self, o: Self) -> Self;
    /// `|self|` per lane.
    fn abs(self) -> Self;
    /// Mask of `self < o`.
    fn lt(self, o: Self) -> Self;
    /// Mask of `self <= o`.
    fn le(self, o: Self) -> Self;
    /// Bitwise and.
    fn and(self, o: Self) -> Self;
    /// `mask ? a : b` per lane, `self` the mask.
    fn select(self, a: Self, b: Self) -> Self;
    /// Lane `i`'s sign bit in bit `i`.
    fn bits(self) -> u32;
    /// `self / o` per lane (correctly rounded, not a reciprocal estimate).
    fn div(self, o: Self) -> Self;
    /// `-self` per lane (the sign bit flipped).
    fn neg(self) -> Self;
    /// Mask of `self > o`.
    fn gt(self, o: Self) -> Self;
    /// Mask of `self >= o`.
    fn ge(self, o: Self) -> Self;
    /// Mask of `self == o`.
    fn eq(self, o: Self) -> Self;
    /// Bitwise or.
    fn or(self, o: Self) -> Self;
    /// The eight columns of the 8x8 matrix whose rows are `rows`: column `c` has
    /// `rows[j][c]` in lane `j`.
    fn columns(rows: [&[f32; 8]; 8]) -> [Self; 8];
    /// The eight rows of the 8x4 matrix whose columns are `cols`: row `j` is lane `j` of
    /// each column.
    fn rows4(cols: [Self; 4]) -> [[f32; 4]; 8];
    /// Writes the values of `values` whose bit is set in `lanes` (eight bits) to the first
    /// slots of `out`, in lane order; the other slots of `out` are left unspecified.
    fn compress(lanes: u32, values: &[u32; 8], out: &mut [u32; 8]);
}

/// For each eight-bit lane mask, the set lanes' indices in order, three bits each (the
/// first in bits 0-2): what [`Wide::compress`] permutes by.
const COMPRESS: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut mask = 0;
    while mask < 256 {
        let (mut lane, mut k, mut packed) = (0, 0, 0u32);
        while lane < 8 {
            if mask >> lane & 1 != 0 {
                packed |= (lane as u32) << (3 * k);
                k += 1;
            }
            lane += 1;
        }
        table[mask] = packed;
        mask += 1;
    }
    table
};

/// Eight lanes as two of four: the portable and SSE paths' [`Wide`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Pair<L>(L, L);

impl<L: Lanes> Pair<L> {
    #[inline(always)]
    fn both(self, o: Self, f: impl Fn(L, L) -> L) -> Self {
        Pair(f(self.0, o.0), f(self.1, o.1))
    }
}

impl<L: Lanes> Wide for Pair<L> {
    #[inline(always)]
    fn splat(x: f32) -> Self {
        Pair(L::splat(x), L::splat(x))
    }
    #[inline(always)]
    fn load(a: &[f32; 8]) -> Self {
        let (lo, hi) = a.split_at(4);
        Pair(
            L::load(lo.try_into().expect("four lanes")),
            L::load(hi.try_into().expect("four lanes")),
        )
    }
    #[inline(always)]
    fn store(self) -> [f32; 8] {
        let (lo, hi) = (self.0.store(), self.1.store());
        std::array::from_fn(|i| if i < 4 { lo[i] } else { hi[i - 4] })
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.both(o, L::add)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.both(o, L::sub)
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.both(o, L::mul)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        self.both(o, L::min)
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.both(o, L::max)
    }
    #[inline(always)]
    fn abs(self) -> Self {
        Pair(self.0.abs(), self.1.abs())
    }
    #[inline(always)]
    fn lt(self, o: Self) -> Self {
        self.both(o, L::lt)
    }
    #[inline(always)]
    fn le(self, o: Self) -> Self {
        self.both(o, L::le)
    }
    #[inline(always)]
    fn and(self, o: Self) -> Self {
        self.both(o, L::and)
    }
    #[inline(always)]
    fn select(self, a: Self, b: Self) -> Self {
        Pair(self.0.select(a.0, b.0), self.1.select(a.1, b.1))
    }
    #[inline(always)]
    fn bits(self) -> u32 {
        self.0.bits() | self.1.bits() << 4
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self.both(o, L::div)
    }
    #[inline(always)]
    fn neg(self) -> Self {
        Pair(self.0.neg(), self.1.neg())
    }
    #[inline(always)]
    fn gt(self, o: Self) -> Self {
        self.both(o, L::gt)
    }
    #[inline(always)]
    fn ge(self, o: Self) -> Self {
        self.both(o, L::ge)
    }
    #[inline(always)]
    fn eq(self, o: Self) -> Self {
        self.both(o, L::eq)
    }
    #[inline(always)]
    fn or(self, o: Self) -> Self {
        self.both(o, L::or)
    }
    #[inline(always)]
    fn rows4(cols: [Self; 4]) -> [[f32; 4]; 8] {
        let c = [
            cols[0].store(),
            cols[1].store(),
            cols[2].store(),
            cols[3].store(),
        ];
        std::array::from_fn(|j| [c[0][j], c[1][j], c[2][j], c[3][j]])
    }
    #[inline(always)]
    fn compress(lanes: u32, values: &[u32; 8], out: &mut [u32; 8]) {
        let packed = COMPRESS[(lanes & 0xff) as usize];
        for (k, slot) in out.iter_mut().enumerate().take(lanes.count_ones() as usize) {
            *slot = values[(packed >> (3 * k) & 7) as usize];
        }
    }
    #[inline(always)]
    fn columns(rows: [&[f32; 8]; 8]) -> [Self; 8] {
        std::array::from_fn(|c| {
            Pair(
                L::load(&[rows[0][c], rows[1][c], rows[2][c], rows[3][c]]),
                L::load(&[rows[4][c], rows[5][c], rows[6][c], rows[7][c]]),
            )
        })
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use avx::Avx8;

/// AVX lanes: one 256-bit register per eight lanes.
///
/// Every method uses AVX instructions, so an `Avx8` value must only exist where the CPU
/// has AVX: the walks are instantiated with it only inside `run_avx2`, which runs after
/// AVX2 was detected, and nothing else in the crate names the type.
#[cfg(target_arch = "x86_64")]
mod avx {
    use std::arch::x86_64::*;

    use super::{COMPRESS, Wide};

    /// Eight lanes in an AVX register (see the module docs for where it may be used).
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx8(__m256);

    /// Wraps one AVX operation.
    macro_rules! avx {
        ($e:expr) => {
            // SAFETY: `Avx8` is used only where AVX2 (so AVX) was detected (module docs).
            unsafe { $e }
        };
    }

    impl Wide for Avx8 {
        #[inline(always)]
        fn splat(x: f32) -> Self {
            avx!(Avx8(_mm256_set1_ps(x)))
        }
        #[inline(always)]
        fn load(a: &[f32; 8]) -> Self {
            // `a` is eight readable f32s; the load is unaligned.
            avx!(Avx8(_mm256_loadu_ps(a.as_ptr())))
        }
        #[inline(always)]
        fn store(self) -> [f32; 8] {
            let mut out = [0.0f32; 8];
            // `out` is eight writable f32s; the store is unaligned.
            avx!(_mm256_storeu_ps(out.as_mut_ptr(), self.0));
            out
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            avx!(Avx8(_mm256_add_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            avx!(Avx8(_mm256_sub_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            avx!(Avx8(_mm256_mul_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // `vminps` returns its second operand when either is NaN or both are equal:
            // `if self < o { self } else { o }`.
            avx!(Avx8(_mm256_min_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            avx!(Avx8(_mm256_max_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn abs(self) -> Self {
            avx!(Avx8(_mm256_and_ps(
                self.0,
                _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff))
            )))
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self {
            avx!(Avx8(_mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0)))
        }
        #[inline(always)]
        fn le(self, o: Self) -> Self {
            avx!(Avx8(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0)))
        }
        #[inline(always)]
        fn and(self, o: Self) -> Self {
            avx!(Avx8(_mm256_and_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn select(self, a: Self, b: Self) -> Self {
            // The mask lanes are all ones or all zeros, so the sign bit decides alike.
            avx!(Avx8(_mm256_blendv_ps(b.0, a.0, self.0)))
        }
        #[inline(always)]
        fn bits(self) -> u32 {
            avx!(_mm256_movemask_ps(self.0) as u32)
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            // `vdivps` is correctly rounded (no reciprocal estimate).
            avx!(Avx8(_mm256_div_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn neg(self) -> Self {
            avx!(Avx8(_mm256_xor_ps(self.0, _mm256_set1_ps(-0.0))))
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self {
            avx!(Avx8(_mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0)))
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Self {
            avx!(Avx8(_mm256_cmp_ps::<_CMP_GE_OQ>(self.0, o.0)))
        }
        #[inline(always)]
        fn eq(self, o: Self) -> Self {
            avx!(Avx8(_mm256_cmp_ps::<_CMP_EQ_OQ>(self.0, o.0)))
        }
        #[inline(always)]
        fn or(self, o: Self) -> Self {
            avx!(Avx8(_mm256_or_ps(self.0, o.0)))
        }
        #[inline(always)]
        fn rows4(cols: [Self; 4]) -> [[f32; 4]; 8] {
            // Interleave the columns in pairs, then pairs of pairs: `q[i]` holds row `i`
            // in its low half and row `i + 4` in its high half.
            let mut out = [[0.0f32; 4]; 8];
            avx!({
                let [a, b, c, d] = [cols[0].0, cols[1].0, cols[2].0, cols[3].0];
                let (ab0, ab1) = (_mm256_unpacklo_ps(a, b), _mm256_unpackhi_ps(a, b));
                let (cd0, cd1) = (_mm256_unpacklo_ps(c, d), _mm256_unpackhi_ps(c, d));
                let q = [
                    _mm256_shuffle_ps::<0x44>(ab0, cd0),
                    _mm256_shuffle_ps::<0xee>(ab0, cd0),
                    _mm256_shuffle_ps::<0x44>(ab1, cd1),
                    _mm256_shuffle_ps::<0xee>(ab1, cd1),
                ];
                // `out` is eight rows of four writable f32s; the stores are unaligned.
                for i in 0..4 {
                    _mm_storeu_ps(out[i].as_mut_ptr(), _mm256_castps256_ps128(q[i]));
                    _mm_storeu_ps(out[i + 4].as_mut_ptr(), _mm256_extractf128_ps::<1>(q[i]));
                }
            });
            out
        }
        #[inline(always)]
        fn compress(lanes: u32, values: &[u32; 8], out: &mut [u32; 8]) {
            // `values` and `out` are eight readable and writable u32s; the load and the
            // store are unaligned. `vpermd` reads the low three bits of each index.
            avx!({
                let packed = _mm256_set1_epi32(COMPRESS[(lanes & 0xff) as usize] as i32);
                let index =
                    _mm256_srlv_epi32(packed, _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21));
                let v = _mm256_loadu_si256(values.as_ptr().cast());
                _mm256_storeu_si256(
                    out.as_mut_ptr().cast(),
                    _mm256_permutevar8x32_epi32(v, index),
                );
            })
        }
        #[inline(always)]
        fn columns(rows: [&[f32; 8]; 8]) -> [Self; 8] {
            // Each row is eight readable f32s; the loads are unaligned. The usual 8x8
            // transpose: pairs of rows interleaved, then quads, then the 128-bit halves.
            avx!({
                // No closure: it would be compiled apart from the AVX2 caller.
                let r = [
                    _mm256_loadu_ps(rows[0].as_ptr()),
                    _mm256_loadu_ps(rows[1].as_ptr()),
                    _mm256_loadu_ps(rows[2].as_ptr()),
                    _mm256_loadu_ps(rows[3].as_ptr()),
                    _mm256_loadu_ps(rows[4].as_ptr()),
                    _mm256_loadu_ps(rows[5].as_ptr()),
                    _mm256_loadu_ps(rows[6].as_ptr()),
                    _mm256_loadu_ps(rows[7].as_ptr()),
                ];
                let t = [
                    _mm256_unpacklo_ps(r[0], r[1]),
                    _mm256_unpackhi_ps(r[0], r[1]),
                    _mm256_unpacklo_ps(r[2], r[3]),
                    _mm256_unpackhi_ps(r[2], r[3]),
                    _mm256_unpacklo_ps(r[4], r[5]),
                    _mm256_unpackhi_ps(r[4], r[5]),
                    _mm256_unpacklo_ps(r[6], r[7]),
                    _mm256_unpackhi_ps(r[6], r[7]),
                ];
                let q = [
                    _mm256_shuffle_ps::<0x44>(t[0], t[2]),
                    _mm256_shuffle_ps::<0xee>(t[0], t[2]),
                    _mm256_shuffle_ps::<0x44>(t[1], t[3]),
                    _mm256_shuffle_ps::<0xee>(t[1], t[3]),
                    _mm256_shuffle_ps::<0x44>(t[4], t[6]),
                    _mm256_shuffle_ps::<0xee>(t[4], t[6]),
                    _mm256_shuffle_ps::<0x44>(t[5], t[7]),
                    _mm256_shuffle_ps::<0xee>(t[5], t[7]),
                ];
                [
                    Avx8(_mm256_permute2f128_ps::<0x20>(q[0], q[4])),
                    Avx8(_mm256_permute2f128_ps::<0x20>(q[1], q[5])),
                    Avx8(_mm256_permute2f128_ps::<0x20>(q[2], q[6])),
                    Avx8(_mm256_permute2f128_ps::<0x20>(q[3], q[7])),
                    Avx8(_mm256_permute2f128_ps::<0x31>(q[0], q[4])),
                    Avx8(_mm256_permute2f128_ps::<0x31>(q[1], q[5])),
                    Avx8(_mm256_permute2f128_ps::<0x31>(q[2], q[6])),
                    Avx8(_mm256_permute2f128_ps::<0x31>(q[3], q[7])),
                ]
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Pair, Portable, Wide};

    /// [`Wide::compress`] of every lane mask: the set lanes' values, in lane order, on
    /// every lane type this CPU runs.
    fn compress_keeps_the_set_lanes<W: Wide>() {
        let values = [11, 22, 33, 44, 55, 66, 77, 88];
        for lanes in 0u32..256 {
            let mut out = [u32::MAX; 8];
            W::compress(lanes, &values, &mut out);
            let want: Vec<u32> = (0..8)
                .filter(|&i| lanes >> i & 1 != 0)
                .map(|i| values[i])
                .collect();
            assert_eq!(&out[..want.len()], &want[..], "lanes {lanes:08b}");
        }
    }

    #[test]
    fn compress_gives_the_set_lanes_in_order() {
        compress_keeps_the_set_lanes::<Pair<Portable>>();
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2.
            unsafe { compress_avx2() }
        }
    }

    /// The AVX lanes' test, compiled with AVX2 enabled.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn compress_avx2() {
        compress_keeps_the_set_lanes::<super::Avx8>();
    }
}
