//! The counting allocator of the `cloi` binary, installed here the same way: the peak follows
//! a large allocation and survives its release; a reset restarts it from the bytes in use.

use cloi_host::map::output::{current_heap_bytes, peak_heap_bytes, reset_peak_heap, CountingAlloc};

#[global_allocator]
static HEAP: CountingAlloc = CountingAlloc;

#[test]
fn peak_heap_follows_allocations() {
    let before = current_heap_bytes().expect("the counting allocator is installed");
    reset_peak_heap();
    let big = vec![1u8; 32 << 20];
    let during = current_heap_bytes().unwrap();
    assert!(
        during >= before + (32 << 20) - (1 << 20),
        "{before} -> {during}"
    );
    let mut grown = big.clone();
    grown.resize(48 << 20, 2);
    let peak = peak_heap_bytes().unwrap();
    assert!(peak >= during + (48 << 20) - (1 << 20), "peak {peak}");
    drop(big);
    drop(grown);
    let after = current_heap_bytes().unwrap();
    assert!(after < peak - (64 << 20), "{after} vs {peak}");
    reset_peak_heap();
    assert!(peak_heap_bytes().unwrap() < peak - (64 << 20));
}
