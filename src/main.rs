//! The `shadowcull` command: a thin layer over the library. Exit status 0 on
//! success, 1 when the work failed (bad input, I/O), 2 on a usage error.

mod cli;

use std::process::ExitCode;

#[global_allocator]
static ALLOCATOR: cli::memory::PhaseNamingAllocator = cli::memory::PhaseNamingAllocator;

fn main() -> ExitCode {
    cli::main()
}
