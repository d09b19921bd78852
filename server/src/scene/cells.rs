//! A scene's bricks as a set of linear cell indices: which bricks the next snapshot must write.

/// Linear cell indices, each once: the bricks a snapshot must rewrite. A bitset rather than a
/// list because under load the same cells are touched turn after turn between snapshots.
#[derive(Default)]
pub struct CellSet {
    bits: Vec<u64>,
    len: usize,
}

impl CellSet {
    pub fn from_cells(cells: &[u32]) -> CellSet {
        let mut set = CellSet::default();
        set.insert_all(cells);
        set
    }

    pub fn insert_all(&mut self, cells: &[u32]) {
        for &c in cells {
            let (word, bit) = ((c / 64) as usize, 1u64 << (c % 64));
            if word >= self.bits.len() {
                self.bits.resize(word + 1, 0);
            }
            if self.bits[word] & bit == 0 {
                self.bits[word] |= bit;
                self.len += 1;
            }
        }
    }

    /// The cells in ascending order; the set is left empty.
    pub fn take_sorted(&mut self) -> Vec<u32> {
        let mut out = Vec::with_capacity(self.len);
        for (w, word) in self.bits.iter_mut().enumerate() {
            let mut bits = std::mem::take(word);
            while bits != 0 {
                out.push(w as u32 * 64 + bits.trailing_zeros());
                bits &= bits - 1;
            }
        }
        self.len = 0;
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_set_keeps_each_cell_once_in_order() {
        let mut set = CellSet::from_cells(&[70, 3, 3, 200_000]);
        set.insert_all(&[64, 70, 0]);
        assert_eq!(set.len, 5);
        assert_eq!(set.take_sorted(), vec![0, 3, 64, 70, 200_000]);
        assert!(set.take_sorted().is_empty());
        set.insert_all(&[5]);
        assert_eq!(set.take_sorted(), vec![5]);
    }
}
