use std::process::ExitCode;

use clap::Parser;

/// Counts heap bytes so that `cloi map` can report its peak (see
/// `cloi_host::map::output::peak_heap_bytes`).
#[global_allocator]
static HEAP: cloi_host::map::output::CountingAlloc = cloi_host::map::output::CountingAlloc;

fn main() -> ExitCode {
    let cli = cloi_host::cli::Cli::parse();
    cli.init_logging();
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    match cloi_host::cli::run(cli, &mut out) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
