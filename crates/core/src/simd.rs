//! Hot loops compiled twice, for the baseline x86-64 the release build targets (SSE2:
//! four `f32` or eight `i16` lanes) and for AVX2 (twice as wide), the second chosen at
//! run time where the CPU has it. Without fused multiply-add the two run the same
//! operations in the same order, lane by lane, so their results are bit for bit the
//! same: the machine changes the time, never the measurement.

/// A free function whose body is compiled for both targets ([module docs](self)); call it
/// as usual. Its loops should be plain element-wise loops over slices, which the
/// compiler vectorises at either width.
#[macro_export]
macro_rules! avx2_or_portable {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn portable($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2($($arg: $ty),*) $(-> $ret)? {
                portable($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2, checked just above.
                return unsafe { avx2($($arg),*) };
            }
            portable($($arg),*)
        }
    };
}

#[cfg(test)]
mod tests {
    crate::avx2_or_portable! {
        /// A scaled sum the compiler vectorises.
        fn axpy(a: f32, x: &[f32], y: &mut [f32]) {
            for (y, x) in y.iter_mut().zip(x) {
                *y += a * x;
            }
        }
    }

    #[test]
    fn both_builds_compute_the_same_bits() {
        let x: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin() * 1e3).collect();
        let mut fast = vec![0.25f32; 1000];
        axpy(1.0 / 3.0, &x, &mut fast);
        let want: Vec<f32> = x.iter().map(|x| 0.25 + (1.0f32 / 3.0) * x).collect();
        assert_eq!(fast, want);
    }
}
