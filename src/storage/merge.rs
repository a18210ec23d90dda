//! A k-way merge of sorted, fallible iterators: the mechanics shared by the external sort and,
//! later, the per-direction merge of received packs with kept voxels.
//!
//! A binary heap holds the head of each source. What to do when two heads have equal keys is a
//! separate parameter, the tie rule: a function from a source's index to a secondary key, smaller
//! first. [`by_source`] (the lower source index first) makes the merge stable: if the sources are
//! consecutive slices of one sequence, equal keys come out in their original order, so merging
//! stably sorted runs gives exactly a stable sort of the whole.
//!
//! Memory: one item per source plus the heap's bookkeeping, whatever the lengths of the sources.
//! The first error any source yields is passed on, and the merge then ends.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// The stable tie rule: on equal keys, the item from the lower-numbered source comes first.
pub fn by_source(source: usize) -> usize {
    source
}

/// Bytes the heap spends per source (its current head), for memory budgets.
pub const fn head_bytes<K, R, T>() -> usize {
    std::mem::size_of::<Head<K, R, T>>()
}

/// One source's current head.
struct Head<K, R, T> {
    key: K,
    rank: R,
    source: usize,
    item: T,
}

impl<K: Ord, R: Ord, T> PartialEq for Head<K, R, T> {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl<K: Ord, R: Ord, T> Eq for Head<K, R, T> {}

impl<K: Ord, R: Ord, T> PartialOrd for Head<K, R, T> {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl<K: Ord, R: Ord, T> Ord for Head<K, R, T> {
    /// Reversed, so that `BinaryHeap` (a max-heap) pops the smallest `(key, rank)`; the source
    /// index settles a tie rule that ranks two sources equal, so the order is always total and
    /// the output reproducible.
    fn cmp(&self, other: &Self) -> Ordering {
        (&other.key, &other.rank, other.source).cmp(&(&self.key, &self.rank, self.source))
    }
}

/// Merges sorted sources into one sorted sequence (see the module header).
pub struct KWayMerge<I, T, K, R, E, KF, TF>
where
    I: Iterator<Item = Result<T, E>>,
{
    sources: Vec<I>,
    heap: BinaryHeap<Head<K, R, T>>,
    key: KF,
    tie: TF,
    /// Set once an error has been passed on, or before the first pull.
    failed: bool,
    started: bool,
}

impl<I, T, K, R, E, KF, TF> KWayMerge<I, T, K, R, E, KF, TF>
where
    I: Iterator<Item = Result<T, E>>,
    K: Ord,
    R: Ord,
    KF: FnMut(&T) -> K,
    TF: FnMut(usize) -> R,
{
    /// Merges `sources`, each sorted by `key`; equal keys are ordered by `tie(source index)`.
    pub fn new(sources: Vec<I>, key: KF, tie: TF) -> Self {
        let heap = BinaryHeap::with_capacity(sources.len());
        KWayMerge {
            sources,
            heap,
            key,
            tie,
            failed: false,
            started: false,
        }
    }

    /// Pulls the next item of `source` into the heap.
    fn refill(&mut self, source: usize) -> Result<(), E> {
        if let Some(next) = self.sources[source].next() {
            let item = next?;
            self.heap.push(Head {
                key: (self.key)(&item),
                rank: (self.tie)(source),
                source,
                item,
            });
        }
        Ok(())
    }
}

impl<I, T, K, R, E, KF, TF> Iterator for KWayMerge<I, T, K, R, E, KF, TF>
where
    I: Iterator<Item = Result<T, E>>,
    K: Ord,
    R: Ord,
    KF: FnMut(&T) -> K,
    TF: FnMut(usize) -> R,
{
    type Item = Result<T, E>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        if !self.started {
            // Filled lazily so that constructing a merge does no I/O.
            self.started = true;
            for source in 0..self.sources.len() {
                if let Err(e) = self.refill(source) {
                    self.failed = true;
                    return Some(Err(e));
                }
            }
        }
        let head = self.heap.pop()?;
        if let Err(e) = self.refill(head.source) {
            self.failed = true;
            return Some(Err(e));
        }
        Some(Ok(head.item))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    type Source = std::vec::IntoIter<Result<(u32, char), String>>;

    fn source(items: &[(u32, char)]) -> Source {
        items.iter().map(|&x| Ok(x)).collect::<Vec<_>>().into_iter()
    }

    fn merged(sources: Vec<Source>, tie: impl FnMut(usize) -> usize) -> Vec<(u32, char)> {
        KWayMerge::new(sources, |x: &(u32, char)| x.0, tie)
            .collect::<Result<_, _>>()
            .unwrap()
    }

    #[test]
    fn merges_in_key_order_with_the_given_tie_rule() {
        let make = || {
            vec![
                source(&[(1, 'a'), (3, 'a'), (3, 'b'), (9, 'a')]),
                source(&[]),
                source(&[(0, 'c'), (3, 'c'), (10, 'c')]),
                source(&[(3, 'd')]),
            ]
        };
        let stable = merged(make(), by_source);
        let keys: Vec<u32> = stable.iter().map(|x| x.0).collect();
        assert_eq!(keys, [0, 1, 3, 3, 3, 3, 9, 10]);
        let threes: String = stable.iter().filter(|x| x.0 == 3).map(|x| x.1).collect();
        assert_eq!(
            threes, "abcd",
            "stable: lower source first, and in order within one"
        );
        let reversed = merged(make(), |s| usize::MAX - s);
        let threes: String = reversed.iter().filter(|x| x.0 == 3).map(|x| x.1).collect();
        assert_eq!(threes, "dcab");
    }

    #[test]
    fn first_error_ends_the_merge() {
        let bad: Source = vec![Ok((2, 'x')), Err("disk".to_string()), Ok((5, 'x'))].into_iter();
        let items: Vec<_> =
            KWayMerge::new(vec![source(&[(1, 'a'), (4, 'a')]), bad], |x| x.0, by_source).collect();
        assert_eq!(items.len(), 2);
        assert_eq!(items[0], Ok((1, 'a')));
        assert_eq!(items[1], Err("disk".to_string()));
    }
}
