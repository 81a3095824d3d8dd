fn main() {
    std::process::exit(omis::cli::main());
}
