//! Which march and network kernels this CPU runs ([`March`], [`Network`]): detected once,
//! capped by `NEPHELE_MARCH` / `NEPHELE_NETWORK` for comparisons.

/// How a band's rays are marched (all give the same frames to the bit; tested).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum March {
    /// One ray at a time along its lattice ([`FastPrepared::march`]): CPUs without AVX2.
    Ray,
    /// 32 rays at a time, one per lane, in four groups of 8 AVX2 lanes ([`avx2::march_wave`]).
    Avx2,
    /// 64 rays at a time, in four groups of 16 AVX-512 lanes ([`avx512::march_wave`]).
    Avx512,
}

impl std::str::FromStr for March {
    type Err = String;
    /// By [`March::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::Avx512, Self::Avx2, Self::Ray].into_iter().find(|m| m.name() == s).ok_or_else(|| "the marches are avx512, avx2 and ray".to_string())
    }
}

/// Whether the CPU has what [`avx512`] is compiled for.
pub(super) fn wide_lanes() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        has!("avx512f") && has!("avx512vl") && has!("avx512bw") && has!("avx512dq") && has!("avx2") && has!("fma") && has!("f16c") && has!("bmi2") && has!("lzcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

impl March {
    /// The widest march this CPU has; `NEPHELE_MARCH=ray|avx2` caps it (for side-by-side
    /// measurements), as does `NEPHELE_SIMD`.
    pub fn detect() -> Self {
        let cap = std::env::var("NEPHELE_MARCH").unwrap_or_default();
        match () {
            _ if cap == "ray" || !Self::Avx2.available() => Self::Ray,
            _ if cap != "avx2" && Self::Avx512.available() => Self::Avx512,
            _ => Self::Avx2,
        }
    }

    /// Whether this CPU runs it (within the cap of `NEPHELE_SIMD`).
    pub fn available(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            use crate::mlp::simd::{Level, level};
            match self {
                Self::Ray => true,
                Self::Avx2 => level() != Level::Portable,
                Self::Avx512 => level() == Level::Avx512 && wide_lanes(),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Self::Ray
        }
    }

    /// Its short name, as `NEPHELE_MARCH` and `bench render --marches` spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ray => "ray",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }

    /// What it does, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Self::Ray => "one ray at a time",
            Self::Avx2 => "32 rays, four groups of 8 AVX2 lanes",
            Self::Avx512 => "64 rays, four groups of 16 AVX-512 lanes",
        }
    }
}

/// The arithmetic of the specular network's tiles ([`MlpKernel::forward_tile`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Network {
    /// f32 throughout: the reference's sums up to fused rounding (~1e-6).
    F32,
    /// The hidden layer in 8 bits ([`MlpKernel::with_int8_hidden`]): CPUs with AVX-512 VNNI
    /// (on lego, 0.94–0.95 of the f32 kernel's time per 640×480 frame, the frame within 2 of
    /// 255 of its, 65.6 dB), or with AVX2 and no AVX-512 (weights in 7 bits; on Zen 3, 0.96
    /// of the time, within 4 of 255, 64.9 dB).
    Int8,
}

impl std::str::FromStr for Network {
    type Err = String;
    /// By [`Network::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::F32, Self::Int8].into_iter().find(|m| m.name() == s).ok_or_else(|| "the networks are f32 and int8".to_string())
    }
}

impl Network {
    /// Int8 where the CPU has it, unless `NEPHELE_NETWORK=f32` (or `NEPHELE_SIMD`) says f32.
    pub fn detect() -> Self {
        if std::env::var("NEPHELE_NETWORK").is_ok_and(|v| v == "f32") || !Self::Int8.available() { Self::F32 } else { Self::Int8 }
    }

    /// Whether this CPU runs it (within the cap of `NEPHELE_SIMD`).
    pub fn available(self) -> bool {
        match self {
            Self::F32 => true,
            #[cfg(target_arch = "x86_64")]
            Self::Int8 => crate::mlp::simd::vnni() || crate::mlp::simd::level() == crate::mlp::simd::Level::Avx2,
            #[cfg(not(target_arch = "x86_64"))]
            Self::Int8 => false,
        }
    }

    /// Its short name, as `NEPHELE_NETWORK` and `bench render --networks` spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Int8 => "int8",
        }
    }

    /// What it does, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Self::F32 => "f32 matrix products",
            Self::Int8 if crate::mlp::simd_vnni() => "hidden layer in 8 bits (AVX-512 VNNI)",
            Self::Int8 => "hidden layer in 8 bits (AVX2; weights in 7 bits)",
        }
    }
}
