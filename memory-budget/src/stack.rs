//! Static worst-case stack of a firmware ELF: the deepest path of the call graph, each function
//! weighing its own frame.
//!
//! Inputs, all produced by the firmware build itself:
//! * the ELF, linked from code compiled with `-Z emit-stack-sizes`: its `.stack_sizes` section
//!   holds every function's static frame (callee-saved registers, spills, locals, outgoing
//!   arguments);
//! * its disassembly by `llvm-objdump` (rustup's `llvm-tools`), for the direct edges: every
//!   branch to another function is an edge, call or tail call (a tail call is counted as if the
//!   caller's frame were still live, which over-approximates), and a call to the function's own
//!   start is recursion; functions that LLVM gives no `.stack_sizes` entry (hand-written
//!   assembly, and a few it skips) weigh the sum of every instruction that moves the stack
//!   pointer down;
//! * the post-LTO LLVM IR of the same build (`--emit=llvm-ir`), for the indirect calls (trait
//!   objects, function pointers): an indirect call may reach every *address-taken* function
//!   (one referenced anywhere other than as the callee of a direct call, e.g. in a vtable or a
//!   `fmt::Argument`) whose LLVM function type equals the call's type. Rust calls a function
//!   pointer only through its own type, so the set holds every possible target.
//!
//! The bound fails (an error, never a guess) on: a cycle (recursion, listed), a reachable
//! function without a frame size that moves the stack pointer, an indirect call in code the IR
//! does not describe, a stack pointer moved by a register amount (a dynamic allocation), a
//! write to `pc` of an unknown shape, or an undecodable instruction.
//!
//! What the bound assumes: the root is entered with an empty stack (aarch32-rt's
//! `_asm_core_start` calls `kmain` right after setting SYS mode's stack pointer), and nothing
//! else runs on that stack (the firmware enables no interrupt; exceptions switch to their own
//! banked stacks; semihosting `svc` traps are served by the debugger or QEMU).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};
use object::{Object, ObjectSection, ObjectSymbol, SymbolKind};

/// The root of the firmware's SYS-mode stack.
pub const ROOT: &str = "kmain";

/// What the analysis found.
#[derive(Clone, Debug, Default)]
pub struct StackBound {
    /// Worst-case bytes of stack used below the root's caller.
    pub bound: u64,
    /// The deepest path from the root: (function, its frame in bytes).
    pub path: Vec<(String, u64)>,
    /// Functions reachable from the root.
    pub reachable: usize,
    /// Indirect call instructions in reachable functions.
    pub indirect_sites: usize,
    /// Call-graph edges added for the indirect calls.
    pub indirect_edges: usize,
}

/// One function of the ELF.
#[derive(Debug)]
struct Function {
    name: String,
    start: u64,
    end: u64,
    frame: Option<u64>,
    /// Called or tail-called functions (indices into the function table).
    direct: BTreeSet<usize>,
    indirect_sites: usize,
    /// Instructions that the checks refused, with the reason.
    refused: Vec<String>,
    /// Bytes of every instruction that moves the stack pointer down (push, vpush, `sub sp`,
    /// pre-indexed store), summed: the frame of straight-line code without a recorded size
    /// (`u64::MAX` past an undecoded one).
    pushed: u64,
}

/// Computes the static stack bound of `elf` from `root`, with the post-LTO IR at `ir`.
///
/// # Errors
/// The files cannot be read, `llvm-objdump` cannot run, or the bound cannot be computed (see
/// the module doc); the message lists every offending function or cycle.
pub fn analyze(elf: &Path, ir: &Path, root: &str) -> Result<StackBound> {
    let bytes = std::fs::read(elf).with_context(|| format!("reading {}", elf.display()))?;
    let mut functions =
        elf_functions(&bytes).with_context(|| format!("parsing {}", elf.display()))?;
    let disassembly = disassemble(elf)?;
    scan_disassembly(&disassembly, &mut functions)?;
    let ir_text =
        std::fs::read_to_string(ir).with_context(|| format!("reading {}", ir.display()))?;
    let ir = parse_ir(&ir_text);
    solve(&functions, &ir, root)
}

/// Function symbols with their frames from `.stack_sizes`.
fn elf_functions(bytes: &[u8]) -> Result<Vec<Function>> {
    let file = object::File::parse(bytes)?;
    let mut frames = HashMap::new();
    let section = file
        .section_by_name(".stack_sizes")
        .context("no .stack_sizes section: build with -Z emit-stack-sizes")?;
    let data = section.data()?;
    let mut at = 0;
    while at < data.len() {
        // Entry: the function's address (a target word, little-endian ARM), then its frame as
        // ULEB128.
        let word = data
            .get(at..at + 4)
            .context("truncated .stack_sizes entry")?;
        let addr = u64::from(u32::from_le_bytes([word[0], word[1], word[2], word[3]]));
        at += 4;
        let (size, used) = uleb128(data.get(at..).unwrap_or(&[]))?;
        at += used;
        frames.insert(addr, size);
    }
    let mut functions = Vec::new();
    for sym in file.symbols() {
        if sym.kind() != SymbolKind::Text || sym.size() == 0 {
            continue;
        }
        let name = sym.name()?.to_owned();
        if name.starts_with('$') {
            continue;
        }
        let start = sym.address() & !1;
        functions.push(Function {
            name,
            start,
            end: start + sym.size(),
            frame: frames.get(&start).copied(),
            direct: BTreeSet::new(),
            indirect_sites: 0,
            refused: Vec::new(),
            pushed: 0,
        });
    }
    functions.sort_by_key(|f| f.start);
    functions.dedup_by_key(|f| f.start);
    Ok(functions)
}

fn uleb128(bytes: &[u8]) -> Result<(u64, usize)> {
    let mut value = 0u64;
    for (i, b) in bytes.iter().enumerate().take(10) {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Ok((value, i + 1));
        }
    }
    bail!("bad ULEB128 in .stack_sizes")
}

/// `llvm-objdump` of rustup's `llvm-tools`, or `$LLVM_OBJDUMP`.
fn objdump_path() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("LLVM_OBJDUMP") {
        return Ok(PathBuf::from(p));
    }
    let out = Command::new("rustc")
        .args(["--print", "sysroot"])
        .output()
        .context("running rustc --print sysroot")?;
    let sysroot = PathBuf::from(String::from_utf8(out.stdout)?.trim());
    let host = Command::new("rustc").arg("-vV").output()?;
    let host = String::from_utf8(host.stdout)?
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_owned))
        .context("rustc -vV has no host line")?;
    let p = sysroot
        .join("lib/rustlib")
        .join(host)
        .join("bin/llvm-objdump");
    if !p.is_file() {
        bail!(
            "{} missing: `rustup component add llvm-tools` (scripts/setup does)",
            p.display()
        );
    }
    Ok(p)
}

fn disassemble(elf: &Path) -> Result<String> {
    let objdump = objdump_path()?;
    let out = Command::new(&objdump)
        .args(["-d", "--no-show-raw-insn"])
        .arg(elf)
        .output()
        .with_context(|| format!("running {}", objdump.display()))?;
    if !out.status.success() {
        bail!(
            "{} failed: {}",
            objdump.display(),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8(out.stdout)?)
}

/// One disassembled line: address, mnemonic, operands (data words have mnemonic `.word`).
fn parse_line(line: &str) -> Option<(u64, &str, &str)> {
    let (addr, rest) = line.split_once(':')?;
    let addr = u64::from_str_radix(addr.trim(), 16).ok()?;
    let mut fields = rest.split('\t').skip(1);
    let mnemonic = fields.next()?.trim();
    let operands = fields.next().unwrap_or("").trim();
    Some((addr, mnemonic, operands))
}

const CONDITIONS: [&str; 16] = [
    "", "eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt",
];

fn is(mnemonic: &str, base: &str) -> bool {
    mnemonic
        .strip_prefix(base)
        .is_some_and(|cond| CONDITIONS.contains(&cond) || cond == "le" || cond == "al")
}

/// Registers written by a `pop {..}` / `ldm ..., {..}` list include `pc`.
fn list_has_pc(operands: &str) -> bool {
    operands
        .split_once('{')
        .and_then(|(_, l)| l.split_once('}'))
        .is_some_and(|(l, _)| l.split(',').any(|r| r.trim() == "pc"))
}

/// Fills each function's direct edges, indirect call count, stack growth and refusals.
fn scan_disassembly(text: &str, functions: &mut [Function]) -> Result<()> {
    let index_of = |addr: u64| functions.binary_search_by_key(&addr, |f| f.start).ok();
    let containing = |addr: u64| {
        let i = functions
            .partition_point(|f| f.start <= addr)
            .checked_sub(1)?;
        (addr < functions.get(i)?.end).then_some(i)
    };
    let lines: Vec<(u64, &str, &str)> = text.lines().filter_map(parse_line).collect();
    let mut updates: Vec<(usize, Update)> = Vec::new();
    for (k, &(addr, mnemonic, operands)) in lines.iter().enumerate() {
        let Some(fi) = containing(addr) else { continue };
        let f = &functions[fi];
        if mnemonic == ".word" || mnemonic == ".short" || mnemonic == ".byte" {
            continue;
        }
        if mnemonic == "<unknown>" {
            updates.push((
                fi,
                Update::Refuse(format!("{addr:x}: undecodable instruction")),
            ));
            continue;
        }
        // Branches with an immediate target: inside the function, or an edge.
        if mnemonic.starts_with('b') && operands.starts_with("0x") {
            let target = operands
                .split_whitespace()
                .next()
                .and_then(|t| u64::from_str_radix(t.trim_start_matches("0x"), 16).ok());
            // A branch with link (or after `mov lr, pc`) is a call even inside the function:
            // to its own start it is recursion.
            let link = is(mnemonic, "bl")
                || is(mnemonic, "blx")
                || k.checked_sub(1)
                    .and_then(|j| lines.get(j))
                    .is_some_and(|(_, m, o)| *m == "mov" && *o == "lr, pc");
            match target {
                Some(t) if link && t == f.start => updates.push((fi, Update::Edge(fi))),
                Some(t) if link && t > f.start && t < f.end => updates.push((
                    fi,
                    Update::Refuse(format!("{addr:x}: call into its own body at {t:x}")),
                )),
                Some(t) if t >= f.start && t < f.end => {}
                Some(t) => match index_of(t) {
                    Some(g) => updates.push((fi, Update::Edge(g))),
                    None => updates.push((
                        fi,
                        Update::Refuse(format!("{addr:x}: branch to {t:x}, not a function start")),
                    )),
                },
                None => updates.push((
                    fi,
                    Update::Refuse(format!("{addr:x}: {mnemonic} {operands}")),
                )),
            }
            continue;
        }
        if is(mnemonic, "bx") || is(mnemonic, "blx") {
            if operands != "lr" {
                updates.push((fi, Update::Indirect));
            }
            continue;
        }
        let dest = operands.split(',').next().unwrap_or("").trim();
        let writes_pc = dest == "pc"
            || ((mnemonic.starts_with("pop") || mnemonic.starts_with("ldm"))
                && list_has_pc(operands));
        if writes_pc {
            let is_return = mnemonic.starts_with("pop")
                || (mnemonic.starts_with("ldm") && operands.starts_with("sp!"))
                || (mnemonic.starts_with("mov") && operands == "pc, lr")
                || (mnemonic.starts_with("ldr") && operands.starts_with("pc, [sp], #"));
            let jump_table = mnemonic.starts_with("ldr") && operands.contains(", lsl #2]");
            if is_return {
            } else if jump_table {
                // The table's words follow the instruction (then, maybe, the literal pool).
                // LLVM's tables jump inside their function, so the words inside it are the
                // table and no edge leaves through it.
                let entries = lines[k + 1..]
                    .iter()
                    .take_while(|(_, m, o)| {
                        *m == ".word"
                            && u64::from_str_radix(o.trim_start_matches("0x"), 16)
                                .is_ok_and(|t| t >= f.start && t < f.end)
                    })
                    .count();
                if entries == 0 {
                    updates.push((
                        fi,
                        Update::Refuse(format!("{addr:x}: jump table without entries")),
                    ));
                }
            } else {
                updates.push((
                    fi,
                    Update::Refuse(format!("{addr:x}: write to pc: {mnemonic} {operands}")),
                ));
            }
            continue;
        }
        // Stack growth (for functions without a recorded frame) and dynamic allocations.
        let on_sp = dest == "sp" || dest == "sp!";
        if mnemonic.starts_with("push")
            || mnemonic.starts_with("vpush")
            || (mnemonic.starts_with("stmdb") && operands.starts_with("sp!"))
            || (mnemonic.starts_with("str")
                && operands.contains("[sp, #-")
                && operands.ends_with("]!"))
            || (mnemonic.starts_with("vstmdb") && operands.starts_with("sp!"))
        {
            updates.push((
                fi,
                Update::Grows(growth(mnemonic, operands).unwrap_or(u64::MAX)),
            ));
        } else if on_sp && mnemonic.starts_with("sub") {
            updates.push((
                fi,
                Update::Grows(growth(mnemonic, operands).unwrap_or(u64::MAX)),
            ));
            let amount = operands.rsplit(',').next().unwrap_or("").trim();
            if !amount.starts_with('#') {
                updates.push((
                    fi,
                    Update::Refuse(format!(
                        "{addr:x}: stack moved by a register: {mnemonic} {operands}"
                    )),
                ));
            }
        } else if on_sp && (mnemonic.starts_with("ldr") || mnemonic.starts_with("msr")) {
            updates.push((
                fi,
                Update::Refuse(format!(
                    "{addr:x}: stack pointer loaded: {mnemonic} {operands}"
                )),
            ));
        }
    }
    for (fi, u) in updates {
        let f = &mut functions[fi];
        match u {
            Update::Edge(g) => {
                f.direct.insert(g);
            }
            Update::Indirect => f.indirect_sites += 1,
            Update::Grows(n) => f.pushed = f.pushed.saturating_add(n),
            Update::Refuse(why) => f.refused.push(why),
        }
    }
    Ok(())
}

enum Update {
    Edge(usize),
    Indirect,
    Grows(u64),
    Refuse(String),
}

/// Bytes that a stack-growing instruction pushes or reserves (`None`: not decoded).
fn growth(mnemonic: &str, operands: &str) -> Option<u64> {
    let list_len = || {
        let (_, l) = operands.split_once('{')?;
        let (l, _) = l.split_once('}')?;
        let mut n = 0;
        for r in l.split(',') {
            let r = r.trim();
            n += match r.split_once('-') {
                Some((a, b)) => {
                    let a: u64 = a.trim_start_matches(['r', 'd', 's']).parse().ok()?;
                    let b: u64 = b.trim_start_matches(['r', 'd', 's']).parse().ok()?;
                    b.checked_sub(a)? + 1
                }
                None => 1,
            };
        }
        Some(n)
    };
    let imm = |text: &str| -> Option<u64> {
        let t = text.trim().trim_start_matches('#');
        match t.strip_prefix("0x") {
            Some(h) => u64::from_str_radix(h, 16).ok(),
            None => t.parse().ok(),
        }
    };
    let width = if operands.contains("{d") { 8 } else { 4 };
    if mnemonic.starts_with("push")
        || mnemonic.starts_with("stmdb")
        || mnemonic.starts_with("vstmdb")
    {
        list_len().map(|n| n * width)
    } else if mnemonic.starts_with("vpush") {
        list_len().map(|n| n * width)
    } else if mnemonic.starts_with("sub") {
        imm(operands.rsplit(',').next()?)
    } else if mnemonic.starts_with("str") {
        let (_, off) = operands.split_once("[sp, #-")?;
        imm(off.trim_end_matches("]!"))
    } else {
        None
    }
}

/// What the IR says about functions: their types, the types of their indirect calls, and which
/// are address-taken.
#[derive(Debug, Default)]
struct Ir {
    /// Function name -> its type (`ret(params)`).
    types: HashMap<String, String>,
    /// Function name -> its indirect calls: the type, and the vtable slot (byte offset) for a
    /// trait-object call.
    indirect: HashMap<String, BTreeSet<(String, Option<u64>)>>,
    /// Functions referenced other than as a direct callee.
    address_taken: BTreeSet<String>,
    /// Functions stored in constant globals, by byte offset (vtables: drop, size, align, then
    /// the methods).
    slots: BTreeMap<u64, BTreeSet<String>>,
    /// Functions referenced by a global whose layout was not decoded: any slot.
    any_slot: BTreeSet<String>,
}

/// Splits at top-level commas (outside (), [], {}, <>, and quotes).
fn split_top(s: &str) -> Vec<&str> {
    let (mut depth, mut quoted, mut from) = (0i32, false, 0);
    let mut out = Vec::new();
    for (i, c) in s.char_indices() {
        match c {
            '"' => quoted = !quoted,
            '(' | '[' | '{' | '<' if !quoted => depth += 1,
            ')' | ']' | '}' | '>' if !quoted => depth -= 1,
            ',' if !quoted && depth == 0 => {
                out.push(s[from..i].trim());
                from = i + 1;
            }
            _ => {}
        }
    }
    let last = s[from..].trim();
    if !last.is_empty() {
        out.push(last);
    }
    out
}

/// The leading type of `s` (`ptr`, `i32`, `{ i32, i32 }`, `[4 x i8]`, `...`).
fn leading_type(s: &str) -> &str {
    let s = s.trim();
    if let Some(open) = s.chars().next().filter(|c| matches!(c, '{' | '[' | '<')) {
        let close = match open {
            '{' => '}',
            '[' => ']',
            _ => '>',
        };
        let mut depth = 0;
        for (i, c) in s.char_indices() {
            if c == open {
                depth += 1;
            } else if c == close {
                depth -= 1;
                if depth == 0 {
                    return &s[..=i];
                }
            }
        }
        return s;
    }
    s.split_whitespace().next().unwrap_or("")
}

/// The trailing type of `s` (the return type before a callee or function name).
fn trailing_type(s: &str) -> &str {
    let s = s.trim_end();
    if let Some(close) = s.chars().last().filter(|c| matches!(c, '}' | ']' | '>')) {
        let open = match close {
            '}' => '{',
            ']' => '[',
            _ => '<',
        };
        let mut depth = 0;
        for (i, c) in s.char_indices().rev() {
            if c == close {
                depth += 1;
            } else if c == open {
                depth -= 1;
                if depth == 0 {
                    return &s[i..];
                }
            }
        }
        return s;
    }
    s.rsplit(char::is_whitespace).next().unwrap_or("")
}

/// The text between the `(` at `open` and its matching `)`.
fn parenthesized(s: &str, open: usize) -> Option<&str> {
    let mut depth = 0;
    for (i, c) in s[open..].char_indices() {
        match c {
            '(' => depth += 1,
            ')' => {
                depth -= 1;
                if depth == 0 {
                    return s.get(open + 1..open + i);
                }
            }
            _ => {}
        }
    }
    None
}

fn signature(ret: &str, params: &str) -> String {
    let params: Vec<&str> = split_top(params).into_iter().map(leading_type).collect();
    format!("{}({})", ret, params.join(","))
}

/// A global name at the start of `s` (after `@`), quoted or not.
fn global_name(s: &str) -> (&str, usize) {
    if let Some(q) = s.strip_prefix('"') {
        let end = q.find('"').unwrap_or(q.len());
        return (&q[..end], end + 2);
    }
    let end = s
        .find(|c: char| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '$' | '-')))
        .unwrap_or(s.len());
    (&s[..end], end)
}

/// Records the functions that a constant global holds, at their byte offsets when its layout is
/// a packed struct or array of byte arrays and pointers (rustc's vtables), else at any slot.
fn global_slots(line: &str, ir: &mut Ir) {
    if !line.contains("ptr @") {
        return;
    }
    let body = line
        .split_once(" constant <{ ")
        .and_then(|(_, r)| r.split_once("}> <{ "))
        .and_then(|(_, r)| r.rsplit_once(" }>"))
        .map(|(b, _)| b);
    let mut decoded = Vec::new();
    let mut offset = 0u64;
    let ok = body.is_some_and(|body| {
        split_top(body).into_iter().all(|element| {
            if let Some(f) = element.strip_prefix("ptr @") {
                decoded.push((offset, global_name(f).0.to_owned()));
                offset += 4;
                true
            } else if element.starts_with("ptr ") {
                offset += 4;
                true
            } else if let Some(n) = element
                .strip_prefix('[')
                .and_then(|r| r.split_once(" x i8]"))
                .and_then(|(n, _)| n.parse::<u64>().ok())
            {
                offset += n;
                true
            } else {
                false
            }
        })
    });
    if ok {
        for (k, f) in decoded {
            ir.slots.entry(k).or_default().insert(f);
        }
    } else {
        let mut rest = line;
        while let Some(at) = rest.find("ptr @") {
            let (name, used) = global_name(&rest[at + 5..]);
            ir.any_slot.insert(name.to_owned());
            rest = &rest[at + 5 + used..];
        }
    }
}

fn parse_ir(text: &str) -> Ir {
    let mut ir = Ir::default();
    let mut current: Option<String> = None;
    let mut references: Vec<(String, bool)> = Vec::new();
    // In the current function: `%p = getelementptr i8, ptr %v, i32 K` -> K, and `%f = load ptr,
    // ptr %p, ..., !invariant.load` (how rustc reads a vtable) -> the offset of `%p`.
    let mut geps: HashMap<String, u64> = HashMap::new();
    let mut vtable_loads: HashMap<String, u64> = HashMap::new();
    for line in text.lines() {
        if line.starts_with('@') {
            global_slots(line, &mut ir);
        }
        if let Some((value, rhs)) = line.trim_start().split_once(" = ") {
            if value.starts_with('%') {
                if let Some(k) = rhs
                    .strip_prefix("getelementptr inbounds nuw i8, ptr ")
                    .or_else(|| rhs.strip_prefix("getelementptr inbounds i8, ptr "))
                    .and_then(|r| r.split(", ").nth(1))
                    .and_then(|k| k.strip_prefix("i32 "))
                    .and_then(|k| k.split(',').next())
                    .and_then(|k| k.trim().parse().ok())
                {
                    geps.insert(value.to_owned(), k);
                } else if rhs.starts_with("load ptr, ptr %") && rhs.contains("!invariant.load") {
                    let from = rhs["load ptr, ptr ".len()..]
                        .split(',')
                        .next()
                        .unwrap_or("");
                    let k = geps.get(from).copied().unwrap_or(0);
                    vtable_loads.insert(value.to_owned(), k);
                }
            }
        }
        let head = line.starts_with("define ") || line.starts_with("declare ");
        if head {
            if let Some(at) = line.find(" @") {
                let (name, used) = global_name(&line[at + 2..]);
                let open = at + 2 + used;
                if line[open..].starts_with('(') {
                    let params = parenthesized(line, open).unwrap_or("");
                    let ret = trailing_type(&line[..at]);
                    ir.types.insert(name.to_owned(), signature(ret, params));
                }
                current = line.starts_with("define ").then(|| name.to_owned());
                geps.clear();
                vtable_loads.clear();
            }
            continue;
        }
        if line == "}" {
            current = None;
            continue;
        }
        if line.starts_with('!') || line.starts_with("attributes ") {
            continue;
        }
        // Every `@name` on the line: a direct callee when followed by `(`, else a reference.
        let mut rest = line;
        let mut offset = 0;
        while let Some(at) = rest.find('@') {
            let (name, used) = global_name(&rest[at + 1..]);
            let after = &rest[at + 1 + used..];
            references.push((name.to_owned(), after.starts_with('(')));
            offset += at + 1 + used;
            rest = &line[offset..];
        }
        // Indirect calls: `call [attributes] <ret> %callee(<args>)`; attributes hold no `%`
        // or `@`, so the first of them starts the callee.
        if let (Some(func), Some(call)) = (&current, line.find("call ")) {
            let after = &line[call + 5..];
            if let Some(at) = after.find(['%', '@']).filter(|_| !after.contains(" asm ")) {
                let callee_and_args = &after[at..];
                let (_, used) = global_name(&callee_and_args[1..]);
                let open = used + 1;
                let callee = &callee_and_args[..open];
                if after[at..].starts_with('%') && callee_and_args[open..].starts_with('(') {
                    let before = after[..at].trim_end();
                    let sig = if before.ends_with(')') {
                        // An explicit function type, `ret (params)`.
                        let open_t = before.rfind('(').unwrap_or(0);
                        signature(
                            trailing_type(&before[..open_t]),
                            &before[open_t + 1..before.len() - 1],
                        )
                    } else {
                        let args = parenthesized(callee_and_args, open).unwrap_or("");
                        signature(trailing_type(before), args)
                    };
                    let slot = vtable_loads.get(callee).copied();
                    ir.indirect
                        .entry(func.clone())
                        .or_default()
                        .insert((sig, slot));
                }
            }
        }
    }
    for (name, called) in references {
        if !called && ir.types.contains_key(&name) && !name.starts_with("llvm.") {
            ir.address_taken.insert(name);
        }
    }
    ir
}

fn solve(functions: &[Function], ir: &Ir, root: &str) -> Result<StackBound> {
    let by_name: HashMap<&str, usize> = functions
        .iter()
        .enumerate()
        .map(|(i, f)| (f.name.as_str(), i))
        .collect();
    let root_i = *by_name
        .get(root)
        .with_context(|| format!("no function {root} in the ELF"))?;
    // Address-taken functions by type.
    let mut by_type: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for name in &ir.address_taken {
        if let Some(t) = ir.types.get(name) {
            by_type.entry(t).or_default().push(name);
        }
    }
    let mut problems = Vec::new();
    let mut edges: Vec<BTreeSet<usize>> = functions.iter().map(|f| f.direct.clone()).collect();
    let (mut reachable, mut stack) = (vec![false; functions.len()], vec![root_i]);
    let (mut indirect_sites, mut indirect_edges) = (0, 0);
    while let Some(i) = stack.pop() {
        if reachable[i] {
            continue;
        }
        reachable[i] = true;
        let f = &functions[i];
        for why in &f.refused {
            problems.push(format!("{}: {why}", f.name));
        }
        if f.indirect_sites > 0 {
            indirect_sites += f.indirect_sites;
            match ir.indirect.get(&f.name) {
                None => problems.push(format!(
                    "{}: {} indirect call(s) that the IR does not describe",
                    f.name, f.indirect_sites
                )),
                Some(calls) => {
                    for (t, slot) in calls {
                        let typed = by_type.get(t.as_str()).into_iter().flatten();
                        let candidates: Vec<&&str> = match slot {
                            // A trait-object call reaches only what a vtable holds at that slot.
                            Some(k) => typed
                                .filter(|g| {
                                    ir.slots.get(k).is_some_and(|s| s.contains(**g))
                                        || ir.any_slot.contains(**g)
                                })
                                .collect(),
                            None => typed.collect(),
                        };
                        for target in candidates {
                            match by_name.get(target) {
                                Some(&g) => {
                                    if edges[i].insert(g) {
                                        indirect_edges += 1;
                                    }
                                }
                                None => problems.push(format!(
                                    "{}: possible indirect target {target} is not in the ELF",
                                    f.name
                                )),
                            }
                        }
                    }
                }
            }
        }
        stack.extend(edges[i].iter().copied());
    }
    // Without a recorded frame (hand-written assembly), the sum of the function's pushes and
    // reservations: a bound for code that does not loop around a push.
    let frame = |i: usize| -> Option<u64> {
        let f = &functions[i];
        f.frame.or((f.pushed != u64::MAX).then_some(f.pushed))
    };
    for (i, f) in functions.iter().enumerate() {
        if reachable[i] && frame(i).is_none() {
            problems.push(format!(
                "{}: no frame size in .stack_sizes and an undecoded push",
                f.name
            ));
        }
    }
    let cycles = cycles(&edges, &reachable);
    for c in &cycles {
        let names: Vec<&str> = c.iter().map(|&i| functions[i].name.as_str()).collect();
        problems.push(format!("recursion: {}", names.join(" -> ")));
    }
    if !problems.is_empty() {
        problems.sort();
        problems.dedup();
        bail!(
            "the static stack bound cannot be computed:\n  {}",
            problems.join("\n  ")
        );
    }
    // Longest path in the (acyclic) reachable graph, memoised in post-order.
    let mut depth: Vec<Option<(u64, Option<usize>)>> = vec![None; functions.len()];
    let mut work = vec![(root_i, false)];
    while let Some((i, expanded)) = work.pop() {
        if depth[i].is_some() {
            continue;
        }
        if expanded {
            let best = edges[i]
                .iter()
                .filter_map(|&g| depth[g].map(|(d, _)| (d, g)))
                .max();
            let own = frame(i).unwrap_or(0);
            depth[i] = Some((own + best.map_or(0, |(d, _)| d), best.map(|(_, g)| g)));
        } else {
            work.push((i, true));
            work.extend(
                edges[i]
                    .iter()
                    .filter(|&&g| depth[g].is_none())
                    .map(|&g| (g, false)),
            );
        }
    }
    let mut path = Vec::new();
    let mut at = Some(root_i);
    while let Some(i) = at {
        path.push((functions[i].name.clone(), frame(i).unwrap_or(0)));
        at = depth[i].and_then(|(_, next)| next);
    }
    Ok(StackBound {
        bound: depth[root_i].map_or(0, |(d, _)| d),
        path,
        reachable: reachable.iter().filter(|&&r| r).count(),
        indirect_sites,
        indirect_edges,
    })
}

/// Every cycle among reachable functions, one per strongly connected component (Tarjan).
fn cycles(edges: &[BTreeSet<usize>], reachable: &[bool]) -> Vec<Vec<usize>> {
    struct State<'a> {
        edges: &'a [BTreeSet<usize>],
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        on_stack: Vec<bool>,
        stack: Vec<usize>,
        next: usize,
        out: Vec<Vec<usize>>,
    }
    let n = edges.len();
    let mut s = State {
        edges,
        index: vec![None; n],
        low: vec![0; n],
        on_stack: vec![false; n],
        stack: Vec::new(),
        next: 0,
        out: Vec::new(),
    };
    // Iterative Tarjan: (node, next edge position).
    for v in (0..n).filter(|&v| reachable[v]) {
        if s.index[v].is_some() {
            continue;
        }
        let mut call: Vec<(usize, usize)> = vec![(v, 0)];
        s.index[v] = Some(s.next);
        s.low[v] = s.next;
        s.next += 1;
        s.stack.push(v);
        s.on_stack[v] = true;
        while let Some(&mut (u, ref mut pos)) = call.last_mut() {
            let next = s.edges[u].iter().nth(*pos).copied();
            *pos += 1;
            match next {
                Some(w) if s.index[w].is_none() => {
                    s.index[w] = Some(s.next);
                    s.low[w] = s.next;
                    s.next += 1;
                    s.stack.push(w);
                    s.on_stack[w] = true;
                    call.push((w, 0));
                }
                Some(w) => {
                    if s.on_stack[w] {
                        s.low[u] = s.low[u].min(s.index[w].unwrap_or(usize::MAX));
                    }
                }
                None => {
                    call.pop();
                    if let Some(&(parent, _)) = call.last() {
                        s.low[parent] = s.low[parent].min(s.low[u]);
                    }
                    if Some(s.low[u]) == s.index[u] {
                        let mut comp = Vec::new();
                        while let Some(w) = s.stack.pop() {
                            s.on_stack[w] = false;
                            comp.push(w);
                            if w == u {
                                break;
                            }
                        }
                        if comp.len() > 1 || s.edges[u].contains(&u) {
                            comp.reverse();
                            s.out.push(comp);
                        }
                    }
                }
            }
        }
    }
    s.out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ir_types_calls_and_address_taken() {
        let ir = parse_ir(
            "@vt = constant <{ ptr, ptr }> <{ ptr @a, ptr @b }>\n\
             define internal noundef zeroext i1 @a(ptr %x, ptr noalias align 4 %f) {\n\
             \x20 %r = call noundef zeroext i1 %p(ptr noundef nonnull %x, ptr align 4 %f)\n\
             \x20 call void @c(i32 1)\n\
             \x20 ret i1 %r\n}\n\
             define void @b(i32 %x) {\n  ret void\n}\n\
             define void @c(i32 %x) {\n  ret void\n}\n\
             declare void @llvm.trap()\n",
        );
        assert_eq!(ir.types["a"], "i1(ptr,ptr)");
        assert_eq!(ir.types["b"], "void(i32)");
        assert_eq!(
            ir.indirect["a"],
            BTreeSet::from([("i1(ptr,ptr)".to_owned(), None)])
        );
        assert_eq!(ir.slots[&0], BTreeSet::from(["a".to_owned()]));
        assert_eq!(ir.slots[&4], BTreeSet::from(["b".to_owned()]));
        assert_eq!(
            ir.address_taken,
            BTreeSet::from(["a".to_owned(), "b".to_owned()])
        );
    }

    #[test]
    fn trait_object_calls_know_their_slot() {
        let ir = parse_ir(
            "define void @f(ptr %self, ptr %vt) {\n\
             \x20 %4 = getelementptr inbounds nuw i8, ptr %vt, i32 12, !dbg !1\n\
             \x20 %5 = load ptr, ptr %4, align 4, !invariant.load !2, !nonnull !2\n\
             \x20 %6 = tail call noundef zeroext i1 %5(ptr %self, ptr dereferenceable(16) %x)\n\
             \x20 ret void\n}\n",
        );
        assert_eq!(
            ir.indirect["f"],
            BTreeSet::from([("i1(ptr,ptr)".to_owned(), Some(12))])
        );
    }

    #[test]
    fn finds_recursion_through_a_cycle() {
        let edges = vec![
            BTreeSet::from([1]),
            BTreeSet::from([2]),
            BTreeSet::from([1]),
            BTreeSet::from([3]),
        ];
        let found = cycles(&edges, &[true, true, true, true]);
        assert_eq!(found, vec![vec![1, 2], vec![3]]);
    }

    #[test]
    fn disassembly_edges_returns_and_refusals() {
        let mut fs = vec![
            Function {
                name: "f".into(),
                start: 0x100,
                end: 0x120,
                frame: Some(16),
                direct: BTreeSet::new(),
                indirect_sites: 0,
                refused: Vec::new(),
                pushed: 0,
            },
            Function {
                name: "g".into(),
                start: 0x120,
                end: 0x128,
                frame: None,
                direct: BTreeSet::new(),
                indirect_sites: 0,
                refused: Vec::new(),
                pushed: 0,
            },
        ];
        let text = "00000100 <f>:\n\
             \x20    100:      \tpush\t{r4, lr}\n\
             \x20    104:      \tbl\t0x120 <g> @ imm = #0x10\n\
             \x20    108:      \tbeq\t0x104 <f+0x4> @ imm = #-0xc\n\
             \x20    10a:      \tbl\t0x100 <f> @ imm = #-0xc\n\
             \x20    10c:      \tblx\tr3\n\
             \x20    110:      \tsub\tsp, sp, r2\n\
             \x20    114:      \tpop\t{r4, pc}\n\
             00000120 <g>:\n\
             \x20    120:      \tmov\tpc, r1\n\
             \x20    124:      \tbx\tlr\n";
        scan_disassembly(text, &mut fs).unwrap();
        assert_eq!(fs[0].direct, BTreeSet::from([0, 1]), "self-call and call");
        assert_eq!(fs[0].indirect_sites, 1);
        assert_eq!(fs[0].pushed, u64::MAX, "a push of a register amount");
        assert_eq!(fs[0].refused.len(), 1, "{:?}", fs[0].refused);
        assert_eq!(fs[1].refused.len(), 1, "{:?}", fs[1].refused);
        assert_eq!(fs[1].pushed, 0);
        assert_eq!(growth("push", "{r4, r5, r11, lr}"), Some(16));
        assert_eq!(growth("vpush", "{d8, d9}"), Some(16));
        assert_eq!(growth("sub", "sp, sp, #2112"), Some(2112));
        assert_eq!(growth("str", "r12, [sp, #-0x4]!"), Some(4));
    }
}
