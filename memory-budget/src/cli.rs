//! The budget command, shared by `cargo run -p cloi-budget` and `cloi budget`.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use crate::{elf, footprint, stack};

/// Options of the budget command.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct BudgetArgs {
    /// Also check this firmware ELF: section sizes and no allocator linked.
    #[arg(long)]
    pub elf: Option<PathBuf>,
    /// A firmware run log holding a `stack_used_bytes=N` line, for the stack high-water mark.
    #[arg(long, requires = "elf")]
    pub run_log: Option<PathBuf>,
    /// The post-LTO LLVM IR of the same firmware build (`--emit=llvm-ir`): compute the static
    /// worst-case stack (call graph and frame sizes) and fail if it exceeds the stack budget or
    /// cannot be computed. The ELF must be built with `-Z emit-stack-sizes`.
    #[arg(long, requires = "elf")]
    pub stack_ir: Option<PathBuf>,
    /// Fail if the stack high-water mark or the static stack bound exceeds this many bytes.
    #[arg(long, default_value_t = 64 * 1024)]
    pub stack_budget: u64,
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

/// Prints the budget table (and the ELF report) to `out`.
///
/// # Errors
/// A profile exceeds its budget, the ELF links an allocator, the stack exceeds its budget, or
/// a file cannot be read.
pub fn run(args: &BudgetArgs, out: &mut dyn Write) -> Result<()> {
    let profiles = footprint::all_profiles();
    writeln!(
        out,
        "static footprint per profile ({} target, size_of):",
        std::env::consts::ARCH
    )?;
    writeln!(
        out,
        "{:<9} {:>9} {:<22} {:>10} {:>12} {:>12}",
        "profile", "area m2", "pool", "count", "bytes", "MiB"
    )?;
    let mut over = Vec::new();
    for p in &profiles {
        for r in &p.pools {
            writeln!(
                out,
                "{:<9} {:>9} {:<22} {:>10} {:>12} {:>12.3}",
                p.spec.name,
                p.spec.area_m2,
                r.name,
                r.count,
                r.bytes,
                mib(r.bytes as u64)
            )?;
        }
        writeln!(
            out,
            "{:<9} {:>9} {:<22} {:>10} {:>12} {:>12.3}  budget {:.0} MiB: {}",
            p.spec.name,
            p.spec.area_m2,
            "TOTAL",
            "",
            p.total_bytes,
            mib(p.total_bytes as u64),
            mib(p.spec.budget_bytes as u64),
            if p.fits() { "ok" } else { "OVER" }
        )?;
        if !p.fits() {
            over.push(p.spec.name);
        }
    }
    if !over.is_empty() {
        bail!("profiles over budget: {}", over.join(", "));
    }
    if let Some(path) = &args.elf {
        let rep = elf::inspect(path)?;
        writeln!(out, "firmware {}:", path.display())?;
        writeln!(
            out,
            "  .text {} B, .rodata {} B, .data {} B, .bss {} B, stacks {} B, static RAM {} B",
            rep.text,
            rep.rodata,
            rep.data,
            rep.bss,
            rep.stacks,
            rep.static_ram()
        )?;
        if rep.allocator_symbols.is_empty() {
            writeln!(out, "  allocator symbols: none")?;
        } else {
            bail!(
                "{} links a heap allocator: {}",
                path.display(),
                rep.allocator_symbols.join(", ")
            );
        }
        if let Some(log) = &args.run_log {
            let text = std::fs::read_to_string(log)
                .with_context(|| format!("reading run log {}", log.display()))?;
            let used = elf::stack_high_water(&text)
                .with_context(|| format!("{} has no stack_used_bytes= line", log.display()))?;
            writeln!(
                out,
                "  stack high-water {} B (budget {} B)",
                used, args.stack_budget
            )?;
            if used > args.stack_budget {
                bail!(
                    "stack high-water {} B exceeds the budget of {} B",
                    used,
                    args.stack_budget
                );
            }
        }
        if let Some(ir) = &args.stack_ir {
            let sb = stack::analyze(path, ir, stack::ROOT)?;
            writeln!(
                out,
                "  static stack bound {} B from {} ({} functions reachable, {} indirect call \
                 sites -> {} edges, no recursion; budget {} B); deepest path:",
                sb.bound,
                stack::ROOT,
                sb.reachable,
                sb.indirect_sites,
                sb.indirect_edges,
                args.stack_budget
            )?;
            for (name, frame) in &sb.path {
                writeln!(out, "    {frame:>6} B  {name}")?;
            }
            if sb.bound > args.stack_budget {
                bail!(
                    "static stack bound {} B exceeds the budget of {} B",
                    sb.bound,
                    args.stack_budget
                );
            }
        }
    }
    Ok(())
}
