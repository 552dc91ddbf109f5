//! How a buffer's rows lie in GPU memory: `vec4`s for vectors, and corner-major tables for
//! the per-corner vectors an element or triangle kernel writes and a node kernel gathers.

use crate::ir::{BufferId, Module};
use std::borrow::Cow;

/// How a buffer's rows (its `width` values per entity) lie in GPU memory. A row of 3·k values
/// (a node's position, a corner's force: the vectors gathers sum) is k `vec4`s with the fourth
/// lane unused, so a vector is one 16-byte load or store and a gather reads one `vec4` per
/// incidence; other rows of more than 2 values are `vec4`s, the last one partly used; rows
/// of 1 or 2 values are plain.
///
/// A row of one 3-vector per corner of an element or triangle (its corner forces and their
/// adjoints) is stored corner-major in a module for one scene: `vec4` `g` of entity `e` at
/// `g · rows + e`, so the `vec4`s a warp of consecutive entities stores for one corner are
/// consecutive, as `limit.cu` lays them out. Measured on an H200 (2026-11-27, the benchmark
/// step's two kernels alone, GPU time per step): 45.8 → 32.7 µs at 420k tets, 15.4 → 13.0 µs
/// at 50k, 13.3 → 11.9 µs at 10k. A batch keeps entity-major rows (each scene's rows one
/// block, read back per scene).
///
/// The runtime pads what it uploads and drops the padding (and undoes the corner-major
/// order) from what it reads back ([`RowLayout::pad`], [`RowLayout::unpad`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RowLayout {
    /// Values per entity.
    pub width: u32,
    /// Lanes used of each `vec4` (3 or 4); 0 for a plain row.
    pub lanes: u32,
    /// `vec4` `g` of every entity together (entity `e`'s at `g · rows + e`).
    pub corner_major: bool,
}

impl RowLayout {
    /// The entity-major layout of rows of `width` values.
    pub const fn of(width: u32) -> Self {
        let lanes = if width <= 2 {
            0
        } else if width.is_multiple_of(3) {
            3
        } else {
            4
        };
        RowLayout {
            width,
            lanes,
            corner_major: false,
        }
    }

    /// The layout of buffer `b` of `module` in a module for one scene (`batched` false) or a
    /// batch: corner-major for one 3-vector per corner of an element or triangle, in a module
    /// for one scene.
    pub fn of_buffer(module: &Module, b: BufferId, batched: bool) -> Self {
        let buffer = &module.buffers[b.0 as usize];
        let mut layout = Self::of(buffer.width);
        layout.corner_major = !batched
            && layout.lanes == 3
            && module
                .corners(buffer.domain)
                .is_some_and(|nc| buffer.width == 3 * nc);
        layout
    }

    /// Whether the rows are `vec4`s.
    pub const fn is_vector(self) -> bool {
        self.lanes > 0
    }

    /// `vec4`s per row (0 for a plain row).
    pub const fn groups(self) -> u32 {
        if self.is_vector() {
            self.width.div_ceil(self.lanes)
        } else {
            0
        }
    }

    /// Values per entity in GPU memory.
    pub const fn padded(self) -> u32 {
        if self.is_vector() {
            4 * self.groups()
        } else {
            self.width
        }
    }

    /// The `vec4` of the row and the lane holding value `c` of a vector row.
    pub fn place(self, c: u32) -> (u32, u32) {
        (c / self.lanes, c % self.lanes)
    }

    /// Where value `c` of entity `e` of `rows` entities lies among the GPU's values.
    fn gpu_index(self, rows: usize, e: usize, c: usize) -> usize {
        let l = self.lanes as usize;
        let (g, lane) = (c / l, c % l);
        if self.corner_major {
            (g * rows + e) * 4 + lane
        } else {
            e * self.padded() as usize + g * 4 + lane
        }
    }

    /// Rows in GPU layout from rows of `width` values (unused lanes 0); plain rows as they
    /// are.
    pub fn pad(self, values: &[f64]) -> Cow<'_, [f64]> {
        if self.padded() == self.width || self.width == 0 {
            return Cow::Borrowed(values);
        }
        let w = self.width as usize;
        let rows = values.len() / w;
        let mut out = vec![0.0; rows * self.padded() as usize];
        for (e, row) in values.chunks_exact(w).enumerate() {
            for (c, &v) in row.iter().enumerate() {
                out[self.gpu_index(rows, e, c)] = v;
            }
        }
        Cow::Owned(out)
    }

    /// Rows of `width` values from rows in GPU layout; plain rows as they are.
    pub fn unpad(self, values: Vec<f64>) -> Vec<f64> {
        if self.padded() == self.width || self.width == 0 {
            return values;
        }
        let w = self.width as usize;
        let rows = values.len() / self.padded() as usize;
        (0..rows)
            .flat_map(|e| (0..w).map(move |c| (e, c)))
            .map(|(e, c)| values[self.gpu_index(rows, e, c)])
            .collect()
    }
}
