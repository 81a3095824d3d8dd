fn main() {
    // Built for x86-64-v3 (.cargo/config.toml): say so instead of dying on an illegal instruction.
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "avx2",
        target_feature = "fma"
    ))]
    if !(std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma"))
    {
        eprintln!(
            "omis: this binary was built for x86-64-v3 (AVX2 and FMA), which this processor lacks; \
             build it with RUSTFLAGS=\"-C target-cpu=x86-64\""
        );
        std::process::exit(2);
    }
    std::process::exit(omis::cli::main());
}
