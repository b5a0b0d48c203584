//! Runtime CPU dispatch: hot kernels are written once as `#[inline(always)]` generic code and
//! compiled twice, for the baseline target and with AVX2 enabled (chosen at run time).

/// Whether the CPU supports AVX2 and POPCNT (cached by the standard library).
#[inline]
pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `dispatch!(fn name(args) -> ret => body_fn)` defines `name`, calling the
/// `#[inline(always)]` function `body_fn` compiled with AVX2 when available.
macro_rules! dispatch {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($a:ident: $t:ty),* $(,)?) $(-> $r:ty)? => $body:path) => {
        $(#[$m])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($a: $t),*) $(-> $r)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,popcnt")]
                #[allow(clippy::too_many_arguments)]
                fn avx2($($a: $t),*) $(-> $r)? {
                    $body($($a),*)
                }
                if $crate::features::simd::has_avx2() {
                    // SAFETY: the CPU supports AVX2 and POPCNT (checked just above).
                    return unsafe { avx2($($a),*) };
                }
            }
            $body($($a),*)
        }
    };
}
pub(crate) use dispatch;
