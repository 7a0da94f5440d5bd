use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = cloi_host::cli::Cli::parse();
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
