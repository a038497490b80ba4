//! A parallel map over the machine's cores with `std::thread::scope` (no thread pool crate):
//! the benchmarks' beds are independent once drawn, and the order of the results is the
//! order of the inputs, so a parallel run prints the same figures as a serial one.

/// `f` over `items` on every core `std::thread::available_parallelism` reports, in order.
pub(crate) fn par_map<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let threads = std::thread::available_parallelism()
        .map_or(1, std::num::NonZeroUsize::get)
        .min(items.len().max(1));
    if threads <= 1 {
        return items.iter().map(&f).collect();
    }
    // Items are dealt out one at a time (beds differ a lot in how long they take).
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut slots: Vec<Option<R>> = std::iter::repeat_with(|| None).take(items.len()).collect();
    let done = std::sync::Mutex::new(&mut slots);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                let r = f(item);
                done.lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)[i] = Some(r);
            });
        }
    });
    slots.into_iter().flatten().collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_results_come_in_the_order_of_the_inputs() {
        let v: Vec<u64> = (0..1000).collect();
        let out = super::par_map(&v, |x| x * x);
        assert_eq!(out, v.iter().map(|x| x * x).collect::<Vec<_>>());
    }
}
