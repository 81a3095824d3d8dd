fn main() {
    // Built for x86-64-v3 (.cargo/config.toml): say so instead of dying on an illegal instruction.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if !cpu::has_x86_64_v3() {
        eprintln!(
            "omis: this binary was built for x86-64-v3 (AVX2 and FMA), which this processor lacks; \
             build it with RUSTFLAGS=\"-C target-cpu=x86-64\""
        );
        std::process::exit(2);
    }
    std::process::exit(omis::cli::main());
}

/// What the processor runs, asked of the processor itself: `is_x86_feature_detected!` answers
/// true without asking for every feature the build enables, so it cannot check the build.
#[cfg(target_arch = "x86_64")]
mod cpu {
    use std::arch::x86_64::{__cpuid, __cpuid_count};

    /// AVX, AVX2 and FMA with the AVX registers saved by the operating system (CPUID leaves 1
    /// and 7, XCR0 bits 1-2: Intel SDM vol. 1, 14.3).
    #[cfg_attr(not(target_feature = "avx2"), allow(dead_code))]
    pub fn has_x86_64_v3() -> bool {
        let l1 = __cpuid(1);
        let bit = |r: u32, b: u32| r >> b & 1 == 1;
        let (fma, osxsave, avx) = (bit(l1.ecx, 12), bit(l1.ecx, 27), bit(l1.ecx, 28));
        if !(fma && osxsave && avx) || __cpuid(0).eax < 7 {
            return false;
        }
        let avx2 = bit(__cpuid_count(7, 0).ebx, 5);
        let xcr0: u32;
        // SAFETY: XGETBV with ECX = 0 reads XCR0; OSXSAVE (checked above) says it may run.
        unsafe {
            std::arch::asm!("xgetbv", in("ecx") 0, out("eax") xcr0, out("edx") _,
                options(nomem, nostack, preserves_flags));
        }
        avx2 && xcr0 & 0b110 == 0b110
    }

    #[cfg(test)]
    mod tests {
        /// The answer agrees with the operating system's view (/proc/cpuinfo's flags).
        #[cfg(target_os = "linux")]
        #[test]
        fn the_cpuid_answer_agrees_with_the_kernel() {
            let info = std::fs::read_to_string("/proc/cpuinfo").expect("/proc/cpuinfo");
            let flags = info
                .lines()
                .find(|l| l.starts_with("flags"))
                .expect("a flags line");
            let has = |f: &str| flags.split_whitespace().any(|w| w == f);
            assert_eq!(
                super::has_x86_64_v3(),
                has("avx") && has("avx2") && has("fma"),
                "{flags}"
            );
        }
    }
}
