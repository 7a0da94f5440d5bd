use std::process::ExitCode;

use clap::Parser;

/// Static memory footprint of every CLOi-Mapper profile, checked against its budget.
#[derive(Debug, Parser)]
#[command(name = "cloi-budget", version, about)]
struct Args {
    #[command(flatten)]
    budget: cloi_budget::cli::BudgetArgs,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match cloi_budget::cli::run(&args.budget, &mut std::io::stdout().lock()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
