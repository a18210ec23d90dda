//! Disjoint sets over dense labels (a union-find): the pieces a mesh's triangles form
//! (`voxel::enclosed`) and the connected empty space of a grid swept slice by slice
//! (`solve::enclosure`). Sets may grow one label at a time, since the sweep labels its slices as
//! it goes and must stay within a memory allowance.

/// Labels `0..len`, each in one set. The smallest label of a set is its root: a caller that
/// gives a set a meaning by its smallest label (the sweep's outside is label 1) keeps it as the
/// sets are joined.
#[derive(Clone, Debug, Default)]
pub(crate) struct DisjointSets {
    parent: Vec<u32>,
}

impl DisjointSets {
    /// `n` labels, each alone.
    pub(crate) fn new(n: usize) -> Self {
        DisjointSets {
            parent: (0..n as u32).collect(),
        }
    }

    /// A new label, alone.
    pub(crate) fn push(&mut self) -> u32 {
        let label = self.parent.len() as u32;
        self.parent.push(label);
        label
    }

    /// The root of `label`'s set (with path halving: later finds are shorter).
    pub(crate) fn find(&mut self, mut label: u32) -> u32 {
        while self.parent[label as usize] != label {
            let grand = self.parent[self.parent[label as usize] as usize];
            self.parent[label as usize] = grand;
            label = grand;
        }
        label
    }

    /// Joins the sets of `a` and `b`.
    pub(crate) fn union(&mut self, a: u32, b: u32) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b {
            self.parent[a.max(b) as usize] = a.min(b);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::DisjointSets;

    #[test]
    fn sets_join_under_their_smallest_label() {
        let mut sets = DisjointSets::new(6);
        sets.union(4, 5);
        sets.union(5, 2);
        sets.union(3, 1);
        assert_eq!(sets.find(4), 2);
        assert_eq!(sets.find(5), 2);
        assert_eq!(sets.find(3), 1);
        assert_ne!(sets.find(2), sets.find(1));
        let new = sets.push();
        assert_eq!(new, 6);
        sets.union(new, 4);
        sets.union(0, 3);
        assert_eq!(sets.find(6), 2);
        assert_eq!(sets.find(1), 0);
        // A chain joined from its far end still finds the smallest label.
        let mut chain = DisjointSets::new(1000);
        for k in (1..1000).rev() {
            chain.union(k, k - 1);
        }
        assert!((0..1000).all(|k| chain.find(k) == 0));
    }
}
