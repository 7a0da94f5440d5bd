//! Sorting and selection in place, without recursion and without a heap.
//!
//! `core`'s `sort_unstable*` and `select_nth_unstable*` recurse, and a recursive function
//! leaves the firmware's worst-case stack without a static bound (`cloi-budget --stack-ir`
//! refuses a call graph with a cycle). These functions are introsort and introselect with an
//! explicit stack of fixed size:
//! * ranges of at most [`INSERTION_MAX`] elements are insertion-sorted (stable);
//! * longer ones are partitioned around the median of their first, middle and last elements;
//!   the sort continues with the smaller part and keeps the larger one on a stack of
//!   `usize::BITS` ranges, which never fills since every part waiting there is at least twice
//!   the size of the one being worked on (depth at most `log2(len)`);
//! * a range that took more than `2 * log2(len)` partitions is heap-sorted, so the worst case
//!   stays `O(n log n)` comparisons.
//!
//! None of them is stable beyond [`INSERTION_MAX`] elements. A caller whose result must not
//! depend on the algorithm (the deterministic mapper) compares by a total order under which
//! only identical elements are equal.

use core::cmp::Ordering;

/// Longest range sorted by insertion (stable, like `core`'s sort of short slices).
pub const INSERTION_MAX: usize = 20;

/// Ranges waiting on the sort's stack: one per halving of the length, at most.
const STACK: usize = usize::BITS as usize;

/// Sorts `v` by `compare`, which must be a total order.
pub fn sort_by<T>(v: &mut [T], mut compare: impl FnMut(&T, &T) -> Ordering) {
    introsort(v, &mut |a, b| compare(a, b) == Ordering::Less);
}

/// Sorts `v` by the key `key` of each element.
pub fn sort_by_key<T, K: Ord>(v: &mut [T], mut key: impl FnMut(&T) -> K) {
    introsort(v, &mut |a, b| key(a) < key(b));
}

/// Sorts `v` in increasing order.
pub fn sort<T: Ord>(v: &mut [T]) {
    introsort(v, &mut |a, b| a < b);
}

/// Reorders `v` so that the element at `n` is the one a full sort by `compare` would put
/// there, every element before it compares less or equal, and every one after it greater or
/// equal. Nothing happens when `n >= v.len()`.
pub fn select_nth_by<T>(v: &mut [T], n: usize, mut compare: impl FnMut(&T, &T) -> Ordering) {
    let less = &mut |a: &T, b: &T| compare(a, b) == Ordering::Less;
    let (mut lo, mut hi) = (0, v.len());
    if n >= hi {
        return;
    }
    let mut budget = depth_budget(hi);
    loop {
        let Some(range) = v.get_mut(lo..hi) else {
            return;
        };
        if range.len() <= INSERTION_MAX {
            insertion(range, less);
            return;
        }
        if budget == 0 {
            heap(range, less);
            return;
        }
        budget -= 1;
        let p = lo + partition(range, less);
        match n.cmp(&p) {
            Ordering::Equal => return,
            Ordering::Less => hi = p,
            Ordering::Greater => lo = p + 1,
        }
    }
}

/// Partitions allowed per range before it falls back to the heap sort: `2 * log2(len)`.
fn depth_budget(len: usize) -> u32 {
    2 * (usize::BITS - len.leading_zeros())
}

fn introsort<T>(v: &mut [T], less: &mut impl FnMut(&T, &T) -> bool) {
    if v.len() <= INSERTION_MAX {
        insertion(v, less);
        return;
    }
    // Uninitialized storage: nothing to clear on every call.
    let mut stack = heapless::Vec::<(usize, usize, u32), STACK>::new();
    let (mut lo, mut hi) = (0, v.len());
    let mut budget = depth_budget(hi);
    loop {
        if let Some(range) = v.get_mut(lo..hi) {
            if range.len() <= INSERTION_MAX {
                insertion(range, less);
            } else if budget == 0 {
                heap(range, less);
            } else {
                budget -= 1;
                let p = lo + partition(range, less);
                let (small, large) = if p - lo < hi - p {
                    ((lo, p), (p + 1, hi))
                } else {
                    ((p + 1, hi), (lo, p))
                };
                if stack.push((large.0, large.1, budget)).is_err() {
                    // Cannot happen (see the module doc); sorting the part now stays correct.
                    if let Some(part) = v.get_mut(large.0..large.1) {
                        heap(part, less);
                    }
                }
                (lo, hi) = small;
                continue;
            }
        }
        let Some(next) = stack.pop() else {
            return;
        };
        (lo, hi, budget) = next;
    }
}

/// Stable insertion sort.
fn insertion<T>(v: &mut [T], less: &mut impl FnMut(&T, &T) -> bool) {
    for i in 1..v.len() {
        let mut j = i;
        while j > 0 && less(&v[j], &v[j - 1]) {
            v.swap(j, j - 1);
            j -= 1;
        }
    }
}

/// Partitions `v` (at least 3 elements) around the median of its first, middle and last
/// elements; returns the pivot's final index: everything before it is not greater, everything
/// after it is not less. Scans from both ends and swaps the pairs on the wrong sides, so
/// elements equal to the pivot split evenly instead of piling up on one side.
fn partition<T>(v: &mut [T], less: &mut impl FnMut(&T, &T) -> bool) -> usize {
    let last = v.len() - 1;
    let mid = v.len() / 2;
    // Order v[0] <= v[mid] <= v[last], then move the median to the front.
    if less(&v[mid], &v[0]) {
        v.swap(mid, 0);
    }
    if less(&v[last], &v[mid]) {
        v.swap(last, mid);
        if less(&v[mid], &v[0]) {
            v.swap(mid, 0);
        }
    }
    v.swap(0, mid);
    // v[1..i] is not greater than the pivot v[0], v[j + 1..] not less.
    let (mut i, mut j) = (1, last);
    loop {
        while i <= j && less(&v[i], &v[0]) {
            i += 1;
        }
        while i <= j && less(&v[0], &v[j]) {
            j -= 1;
        }
        if i >= j {
            break;
        }
        v.swap(i, j);
        i += 1;
        j -= 1;
    }
    v.swap(0, j);
    j
}

/// Heap sort: `O(n log n)` whatever the input.
fn heap<T>(v: &mut [T], less: &mut impl FnMut(&T, &T) -> bool) {
    let len = v.len();
    for root in (0..len / 2).rev() {
        sift_down(v, root, len, less);
    }
    for end in (1..len).rev() {
        v.swap(0, end);
        sift_down(v, 0, end, less);
    }
}

fn sift_down<T>(v: &mut [T], mut root: usize, end: usize, less: &mut impl FnMut(&T, &T) -> bool) {
    loop {
        let mut child = 2 * root + 1;
        if child >= end {
            return;
        }
        if child + 1 < end && less(&v[child], &v[child + 1]) {
            child += 1;
        }
        if !less(&v[root], &v[child]) {
            return;
        }
        v.swap(root, child);
        root = child;
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use std::vec::Vec;

    fn values() -> impl Strategy<Value = Vec<(i16, u16)>> {
        // Few distinct keys, so that ties are common.
        proptest::collection::vec((-8i16..8, any::<u16>()), 0..600)
    }

    proptest! {
        #[test]
        fn sort_equals_core_sort(mut v in values()) {
            let mut expected = v.clone();
            expected.sort();
            sort(&mut v);
            prop_assert_eq!(v, expected);
        }

        #[test]
        fn sort_by_key_orders_keys_and_keeps_the_elements(mut v in values()) {
            let mut expected = v.clone();
            expected.sort_by_key(|e| e.0);
            sort_by_key(&mut v, |e| e.0);
            prop_assert!(v.windows(2).all(|w| w[0].0 <= w[1].0));
            let mut got = v.clone();
            got.sort();
            expected.sort();
            prop_assert_eq!(got, expected);
        }

        #[test]
        fn short_sorts_are_stable(mut v in proptest::collection::vec((-3i16..3, any::<u16>()), 0..=INSERTION_MAX)) {
            let mut expected = v.clone();
            expected.sort_by_key(|e| e.0);
            sort_by_key(&mut v, |e| e.0);
            prop_assert_eq!(v, expected);
        }

        #[test]
        fn select_nth_equals_core(mut v in values(), n in 0usize..700) {
            let mut expected = v.clone();
            expected.sort();
            let before = v.clone();
            select_nth_by(&mut v, n, Ord::cmp);
            if n < v.len() {
                prop_assert_eq!(v[n], expected[n]);
                prop_assert!(v[..n].iter().all(|e| *e <= v[n]));
                prop_assert!(v[n + 1..].iter().all(|e| *e >= v[n]));
                let mut got = v.clone();
                got.sort();
                prop_assert_eq!(got, expected);
            } else {
                prop_assert_eq!(v, before);
            }
        }
    }

    #[test]
    fn adversarial_inputs_sort() {
        // Sorted, reversed, constant and organ-pipe inputs, long enough for the heap fallback.
        let n = 5000;
        let inputs: [Vec<i32>; 4] = [
            (0..n).collect(),
            (0..n).rev().collect(),
            (0..n).map(|_| 7).collect(),
            (0..n).map(|i| if i < n / 2 { i } else { n - i }).collect(),
        ];
        for mut v in inputs {
            let mut expected = v.clone();
            expected.sort();
            sort(&mut v);
            assert_eq!(v, expected);
        }
    }
}
