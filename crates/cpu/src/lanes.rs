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
}

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

    use super::Wide;

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
    }
}
