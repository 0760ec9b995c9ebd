//! Run-time choice of the vector instruction set the hot loops run on.
//!
//! The warp and landing loops are written once, branch-free, and compiled three times: for
//! baseline x86-64, AVX2 and AVX-512; the widest the CPU has runs. Rust never contracts a multiply
//! and an add into a fused multiply-add, so every path rounds each operation as the baseline does
//! and the results are bit-identical on every CPU (each kernel's tests compare the paths).

use std::sync::OnceLock;

/// An instruction-set level the CPU supports: a value exists only for a level detected at run
/// time, so code holding one may call functions compiled for that level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Simd(Level);

/// The instruction-set levels the loops are compiled for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    Baseline,
    /// AVX2 (256-bit vectors).
    Avx2,
    /// AVX-512 F, BW, VL and DQ (512-bit vectors, 8-bit lanes, f64 to integer conversions), with AVX2.
    Avx512,
}

impl Simd {
    /// The widest level this CPU supports (detected once per process).
    #[inline]
    pub fn detected() -> Simd {
        static DETECTED: OnceLock<Simd> = OnceLock::new();
        *DETECTED.get_or_init(|| {
            let available = Simd::available();
            available.last().copied().unwrap_or(Simd(Level::Baseline))
        })
    }

    /// Every level this CPU supports, baseline first.
    pub fn available() -> Vec<Simd> {
        let mut levels = vec![Simd(Level::Baseline)];
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") {
                levels.push(Simd(Level::Avx2));
            }
            if std::is_x86_feature_detected!("avx2")
                && std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512bw")
                && std::is_x86_feature_detected!("avx512vl")
                && std::is_x86_feature_detected!("avx512dq")
            {
                levels.push(Simd(Level::Avx512));
            }
        }
        levels
    }

    pub fn level(self) -> Level {
        self.0
    }
}

/// Declares copies of the `#[inline(always)]` function `$kernel` (its signature given) compiled for
/// instruction sets beyond the baseline (x86-64 only), one per `copy: "target features"`. Call a
/// copy only where [`Simd::detected`] reports its level; it gives the baseline's results.
macro_rules! compiled_for {
    (
        fn $kernel:ident $(<$($generic:ident: $bound:path),*>)? ($($arg:ident: $type:ty),* $(,)?)
        $(-> $ret:ty)?;
        $copy:ident: $features:literal $(, $more:ident: $more_features:literal)* $(,)?
    ) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        fn $copy $(<$($generic: $bound),*>)? ($($arg: $type),*) $(-> $ret)? {
            $kernel($($arg),*)
        }
        $crate::simd::compiled_for!(
            fn $kernel $(<$($generic: $bound),*>)? ($($arg: $type),*) $(-> $ret)?;
            $($more: $more_features),*
        );
    };
    (fn $kernel:ident $(<$($generic:ident: $bound:path),*>)? ($($arg:ident: $type:ty),* $(,)?) $(-> $ret:ty)?;) => {};
}
pub(crate) use compiled_for;

/// `[kernel, avx2, avx512](arguments)`: the call of the copy ([`compiled_for`]) of `kernel` for the
/// level of `simd` (a [`Simd`]), `kernel` itself at the baseline.
macro_rules! dispatch {
    ($simd:expr, [$kernel:ident, $avx2:ident, $avx512:ident]($($arg:expr),* $(,)?)) => {
        match $simd.level() {
            // SAFETY: a `Simd` of a level exists only where the CPU supports it.
            #[cfg(target_arch = "x86_64")]
            $crate::simd::Level::Avx512 => unsafe { $avx512($($arg),*) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            $crate::simd::Level::Avx2 => unsafe { $avx2($($arg),*) },
            _ => $kernel($($arg),*),
        }
    };
}
pub(crate) use dispatch;
