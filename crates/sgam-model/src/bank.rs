//! A bank of true frames' code grids, and completion by quilting from it.
//!
//! The learned samplers draw a hole's codes cell by cell, and a cube that spans several cells
//! comes out as a blob of mixed codes. The bank draws a hole the way image quilting and
//! nonparametric texture synthesis do (Efros & Leung 1999; Efros & Freeman 2001), at the level of
//! the VQ codes: for every connected hole, the code grids of real frames are searched for the
//! one whose cells around the hole look most like the visible cells around it (at a small shift),
//! and the hole takes that frame's codes. What fills the hole is a piece of a real frame — whole
//! objects, with their shading and their depth — chosen to agree with what the hole borders on.
//!
//! The bank's frames are rendered from *training* scenes with the dataset's camera (height and
//! pitch fixed, so a cell's row fixes its ground distance) at random positions and headings, and
//! encoded by the model's frozen encoder (`VqRefiner::frame_codes`).

use std::io::Read;
use std::path::Path;

use rand::Rng;
use rayon::prelude::*;

use crate::ModelError;

const MAGIC: &[u8; 8] = b"SGAMBANK";
const VERSION: u32 = 1;
/// Magic + six u32 fields.
const HEADER: usize = 8 + 6 * 4;

/// Code grids of true frames, all `rows x cols` cells of one model's codebook.
#[derive(Debug, Clone, PartialEq)]
pub struct CodeBank {
    /// Cells per frame column.
    pub rows: usize,
    /// Cells per frame row.
    pub cols: usize,
    /// Size of the codebook the codes index.
    pub n_embed: usize,
    /// CRC-32 of the codebook the codes index ([`crate::VqRefiner::codebook_crc32`]): a bank
    /// is meaningless with another model's codebook, and is refused there.
    pub codebook_crc32: u32,
    /// `frames x rows x cols` codes, row-major per frame.
    pub codes: Vec<u16>,
}

/// How the bank filled one connected hole (for tests and diagnostics).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BankDraw {
    /// The bank frame the hole's codes came from.
    pub frame: usize,
    /// Its shift in cells (`[dy, dx]`): hole cell `c` took the bank frame's cell `c + shift`.
    pub shift: [i32; 2],
    /// Mean descriptor distance over the hole's border band (lower is a better match).
    pub score: f32,
    /// Cells of the hole (of the tile, with [`BankSearch::tile`]).
    pub cells: usize,
    /// Which hole (0, 1, ... among those filled) the cells belong to: the tiles of one hole
    /// share its number.
    pub hole: usize,
    /// With a pixel distance ([`FillHints::band_distance`]): the source's pixels are taken
    /// this many pixels `[down, right]` of its cells (the band's sub-cell alignment).
    pub offset_px: [i32; 2],
}

/// What a cell filled earlier in the same [`CodeBank::fill_with`] took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pasted {
    /// The bank frame ...
    pub frame: usize,
    /// ... its cell ...
    pub cell: usize,
    /// ... and the pixel offset ([`BankDraw::offset_px`]).
    pub offset_px: [i32; 2],
}

/// What [`CodeBank::fill`] did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BankFill {
    /// One per hole filled, in reading order of their first cells.
    pub draws: Vec<BankDraw>,
    /// Cells of the holes left for later: thin bands along the frame's border
    /// ([`BankSearch::defer_thinner_than`]).
    pub deferred: Vec<usize>,
    /// Where each filled cell's code came from: `[cell, bank frame, bank frame's cell]`.
    pub sources: Vec<[usize; 3]>,
}

impl BankFill {
    /// Every filled cell, `[cell, bank frame, bank frame's cell]`, with the draw it came from
    /// ([`Self::sources`] hold the draws' cells one draw after another).
    pub fn filled_cells(&self) -> impl Iterator<Item = ([usize; 3], &BankDraw)> + '_ {
        let mut rest = &self.sources[..];
        self.draws.iter().flat_map(move |d| {
            let (these, after) = rest.split_at(d.cells.min(rest.len()));
            rest = after;
            these.iter().map(move |s| (*s, d))
        })
    }

    /// Per cell of a `cells`-cell grid, what this fill put there (its source and pixel offset).
    pub fn pasted(&self, cells: usize) -> Vec<Option<Pasted>> {
        let mut out = vec![None; cells];
        for ([cell, frame, source], d) in self.filled_cells() {
            if let Some(o) = out.get_mut(cell) {
                *o = Some(Pasted { frame, cell: source, offset_px: d.offset_px });
            }
        }
        out
    }
}

/// The pixels behind a bank's codes, for a bank built from real frames at the run's own size
/// (a seed's bank): a hole then takes the source frame's pixels, colour and depth, instead of
/// the decoder's drawing of their codes, which for a frame unlike the model's training data is
/// far from them (a Google Earth seed decodes at 13 dB).
#[derive(Debug, Clone)]
pub struct BankPixels {
    /// The frames whose code grids the bank holds, each rolled ([`CodeBank::rolled`]).
    pub bases: Vec<sgam_core::RgbdFrame>,
    /// Rows and columns between two rolled copies (0: not rolled that way).
    pub roll_cells: [usize; 2],
}

impl BankPixels {
    /// The base frame and the cell `[row, column]` of it behind cell `cell` of bank frame
    /// `frame` of `bank` (laid out as [`CodeBank::rolled`] lays it out).
    pub fn source(&self, bank: &CodeBank, frame: usize, cell: usize) -> Option<(&sgam_core::RgbdFrame, [usize; 2])> {
        let (i, at) = self.source_index(bank, frame, cell)?;
        Some((&self.bases[i], at))
    }

    /// [`Self::source`] as the index of the base frame in [`Self::bases`].
    pub fn source_index(&self, bank: &CodeBank, frame: usize, cell: usize) -> Option<(usize, [usize; 2])> {
        let [rr, rc] = rolls(self.roll_cells, [bank.rows, bank.cols]);
        let base = frame / (rr * rc);
        if base >= self.bases.len() {
            return None;
        }
        let (r, c) = ((frame % (rr * rc)) / rc, frame % rc);
        let (dy, dx) = (r * self.roll_cells[0], c * self.roll_cells[1]);
        Some((base, [(cell / bank.cols + dy) % bank.rows, (cell % bank.cols + dx) % bank.cols]))
    }

    /// Per base frame, per `f x f` cell (row-major over the bank's grid): whether every pixel of
    /// the cell has a valid depth. A cell with a pixel missing (a real sensor's hole, a sky, the
    /// holes of a round trip) has nothing whole to give a hole ([`FillHints::source_usable`]).
    pub fn complete_cells(&self, bank: &CodeBank, f: usize) -> Vec<Vec<bool>> {
        self.bases
            .iter()
            .map(|base| {
                let bw = base.width() as usize;
                (0..bank.rows * bank.cols)
                    .map(|cell| {
                        let (cy, cx) = (cell / bank.cols, cell % bank.cols);
                        (cy * f..(cy + 1) * f).all(|y| {
                            (cx * f..(cx + 1) * f).all(|x| {
                                x < bw
                                    && base.depth_m.data.get(y * bw + x).is_some_and(|d| sgam_core::is_valid_depth(*d))
                            })
                        })
                    })
                    .collect()
            })
            .collect()
    }
}

/// Copies per grid of [`CodeBank::rolled`] along rows and columns.
fn rolls(roll_cells: [usize; 2], [rows, cols]: [usize; 2]) -> [usize; 2] {
    let n = |step: usize, len: usize| if step == 0 { 1 } else { len.div_ceil(step).max(1) };
    [n(roll_cells[0], rows), n(roll_cells[1], cols)]
}

/// Search settings of [`CodeBank::fill`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BankSearch {
    /// Width of the band of visible cells around a hole that is matched, in cells.
    pub band: usize,
    /// Horizontal shifts tried, `-max_shift..=max_shift` cells.
    pub max_shift_x: i32,
    /// Vertical shifts tried (rows change the ground distance, so few).
    pub max_shift_y: i32,
    /// The draw is among this many best matches (variety between seeds) ...
    pub top_k: usize,
    /// ... with probabilities `exp(-(score - best) / tau)`.
    pub tau: f32,
    /// Holes of fewer cells keep the codes they were given (the model's most likely ones).
    pub min_cells: usize,
    /// A hole along the frame's border that reaches fewer cells into the frame is deferred:
    /// filling it would commit a sliver of whatever object lies there, and the next step would
    /// have to continue a sliver. Left unfilled (no depth), it widens step by step until a
    /// whole object fits. 0 fills every hole.
    pub defer_thinner_than: usize,
    /// Objects whole or not at all ([`CodeBank::fill_with`] given which codes are plain): the
    /// best matches pay for the objects the hole would cut, and an object of the chosen bank
    /// frame (a 4-connected group of coloured cells) that observed plain ground would cut is left
    /// out of the hole, whose cells there take the bank row's ground. An ablation (docs/MODEL.md,
    /// session 20): off by default.
    pub whole_objects: bool,
    /// A hole of more than `tile x tile` cells is quilted as tiles of that side, each matched
    /// on the cells around it, those tiles filled before it included ([`CodeBank::fill_with`]).
    /// 0 fills a hole in one piece.
    pub tile: usize,
    /// [`Self::defer_thinner_than`] judges runs of missing cells, not holes: along every row
    /// and column, the run of missing cells from a side of the frame waits when it is shorter,
    /// whatever hole it belongs to (a band the camera uncovers is one hole with every crack
    /// it touches, and as a whole neither thin nor short).
    pub defer_runs: bool,
}

impl Default for BankSearch {
    fn default() -> Self {
        Self {
            band: 2,
            max_shift_x: 2,
            max_shift_y: 1,
            top_k: 8,
            tau: 0.02,
            min_cells: 3,
            defer_thinner_than: 3,
            whole_objects: false,
            tile: 0,
            defer_runs: false,
        }
    }
}

impl CodeBank {
    /// A bank of the code grids `grids` (`rows x cols` each), each also rolled up by every
    /// multiple of `roll_cells[0]` rows and left by every multiple of `roll_cells[1]` columns (0:
    /// not rolled that way). Bank frame `(g * rr + i) * rc + j` is grid `g` rolled by `i *
    /// roll_cells[0]` rows and `j * roll_cells[1]` columns (`rr`, `rc`: the copies each way):
    /// with the search's shifts every offset of a grid is within reach. A synthetic bank keeps
    /// its rows in place (a row holds the ground at one distance); a seed's pixels are moved to
    /// the depth around the hole, so any of its rows may fill it.
    pub fn rolled(
        grids: &[Vec<u32>],
        [rows, cols]: [usize; 2],
        roll_cells: [usize; 2],
        n_embed: usize,
        codebook_crc32: u32,
    ) -> Self {
        let [rr, rc] = rolls(roll_cells, [rows, cols]);
        let mut codes = Vec::new();
        for grid in grids.iter().filter(|g| g.len() == rows * cols) {
            for i in 0..rr {
                for j in 0..rc {
                    let (dy, dx) = (i * roll_cells[0], j * roll_cells[1]);
                    for r in 0..rows {
                        let row = (r + dy) % rows;
                        codes.extend((0..cols).map(|c| grid[row * cols + (c + dx) % cols] as u16));
                    }
                }
            }
        }
        Self { rows, cols, n_embed, codebook_crc32, codes }
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.codes.len() / (self.rows * self.cols).max(1)
    }

    /// Whether the bank holds no frame.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The codes of frame `i`, row-major.
    pub fn frame(&self, i: usize) -> &[u16] {
        let n = self.rows * self.cols;
        &self.codes[i * n..(i + 1) * n]
    }

    /// The file's bytes: magic, version, rows, cols, n_embed, frames, codebook CRC (u32 each),
    /// the codes (u16), a CRC-32 of everything before it; little-endian.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(HEADER + self.codes.len() * 2 + 4);
        b.extend_from_slice(MAGIC);
        for v in
            [VERSION, self.rows as u32, self.cols as u32, self.n_embed as u32, self.len() as u32, self.codebook_crc32]
        {
            b.extend_from_slice(&v.to_le_bytes());
        }
        for c in &self.codes {
            b.extend_from_slice(&c.to_le_bytes());
        }
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses [`Self::to_bytes`]: refuses another magic or version, a wrong length or checksum,
    /// and codes outside the codebook.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ModelError> {
        let bad = |msg: String| ModelError::Format { what: "the code bank", msg };
        if bytes.len() < HEADER + 4 || &bytes[..8] != MAGIC {
            return Err(bad("not a code bank (no SGAMBANK header)".into()));
        }
        let u = |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]) as usize;
        if u(8) != VERSION as usize {
            return Err(bad(format!("version {} (this build reads {VERSION})", u(8))));
        }
        let (rows, cols, n_embed, frames, codebook_crc32) = (u(12), u(16), u(20), u(24), u(28) as u32);
        let n = (rows as u128) * (cols as u128) * (frames as u128);
        if rows == 0
            || cols == 0
            || n_embed == 0
            || n_embed > 1 << 16
            || HEADER as u128 + 2 * n + 4 != bytes.len() as u128
        {
            return Err(bad(format!("{rows}x{cols} cells x {frames} frames does not match {} bytes", bytes.len())));
        }
        let body = bytes.len() - 4;
        if crc32fast::hash(&bytes[..body]) != u(body) as u32 {
            return Err(bad("checksum mismatch (the file is damaged)".into()));
        }
        let codes: Vec<u16> = bytes[HEADER..body].chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        if let Some(c) = codes.iter().find(|&&c| c as usize >= n_embed) {
            return Err(bad(format!("code {c} outside a codebook of {n_embed}")));
        }
        Ok(Self { rows, cols, n_embed, codebook_crc32, codes })
    }

    /// Reads a bank file, naming it in errors.
    pub fn read(path: &Path) -> Result<Self, ModelError> {
        let mut bytes = Vec::new();
        std::fs::File::open(path).and_then(|mut f| f.read_to_end(&mut bytes)).map_err(|e| ModelError::io(path, e))?;
        Self::from_bytes(&bytes).map_err(|e| e.in_file(path))
    }

    /// Fills every connected hole of `missing` (row-major `[rows, cols]` cells, 4-connected) in
    /// `codes` from the bank frame (and shift) whose cells over the hole's border band are
    /// nearest to `codes` there, by the L1 distance of the codes' `looks` (any per-code
    /// descriptor, e.g. decoded colour and disparity); the draw is uniform among the
    /// `search.top_k` best. A hole with no visible border takes a random frame unshifted.
    /// Returns one [`BankDraw`] per hole, in reading order of their first cells.
    pub fn fill(
        &self,
        codes: &mut [u32],
        missing: &[bool],
        looks: &[[f32; 4]],
        search: &BankSearch,
        rng: &mut impl Rng,
    ) -> BankFill {
        self.fill_with(codes, missing, looks, &FillHints::default(), search, rng)
    }

    /// [`Self::fill`] with what the caller knows besides the codes ([`FillHints`]).
    ///
    /// With [`BankSearch::tile`], a hole larger than one tile is quilted as tiles (image
    /// quilting's blocks), the tile with the most known cells around it first; a tile is
    /// matched on the observed cells around it and on the cells tiles before it took, so a long
    /// band is not one thin strip of one place but a continuation of what borders each piece.
    pub fn fill_with(
        &self,
        codes: &mut [u32],
        missing: &[bool],
        looks: &[[f32; 4]],
        hints: &FillHints<'_>,
        search: &BankSearch,
        rng: &mut impl Rng,
    ) -> BankFill {
        let plain = hints.plain;
        let (rows, cols) = (self.rows, self.cols);
        if self.is_empty() || codes.len() != rows * cols || missing.len() != rows * cols {
            return BankFill::default();
        }
        let (mut draws, mut deferred, mut sources) = (Vec::new(), Vec::new(), Vec::new());
        // cells still without content: a tile filled is known to the tiles after it
        let mut open = missing.to_vec();
        // what each cell filled here took
        let mut pasted: Vec<Option<Pasted>> = match hints.filled {
            Some(f) if f.len() == rows * cols => f.to_vec(),
            _ => vec![None; rows * cols],
        };
        let mut holes = 0;
        let to_fill = if search.defer_runs {
            let runs = border_runs(missing, rows, cols, search.defer_thinner_than);
            deferred.extend((0..rows * cols).filter(|&i| runs[i]));
            missing.iter().zip(&runs).map(|(m, r)| *m && !r).collect()
        } else {
            missing.to_vec()
        };
        for hole in components(&to_fill, rows, cols) {
            if hole.len() < search.min_cells {
                continue;
            }
            if !search.defer_runs && thin_at_border(&hole, rows, cols, search.defer_thinner_than) {
                deferred.extend_from_slice(&hole);
                continue;
            }
            let mut pieces: Vec<(Vec<usize>, usize)> = tiles(&hole, cols, search.tile)
                .into_iter()
                .map(|p| {
                    let around = band_cells(&p, rows, cols, search.band);
                    (p, around)
                })
                .collect();
            while !pieces.is_empty() {
                // the piece with the largest share of known cells around it (reading order on ties)
                let next = if pieces.len() == 1 {
                    0
                } else {
                    let known = |(p, around): &(Vec<usize>, usize)| {
                        border_band(p, &open, rows, cols, search.band).len() as f32 / (*around).max(1) as f32
                    };
                    let scores: Vec<f32> = pieces.iter().map(known).collect();
                    (0..pieces.len()).fold(0, |b, j| if scores[j] > scores[b] { j } else { b })
                };
                let (piece, _) = pieces.remove(next);
                // without tiles, a hole is matched on what was observed only, as before tiles
                let seen = if search.tile == 0 { missing } else { &open };
                let (frame, shift, offset_px, score) =
                    self.draw_piece(&piece, codes, seen, &pasted, looks, hints, search, rng);
                let grid = self.frame(frame);
                let cut = match plain {
                    Some(plain) if search.whole_objects => cut_objects(grid, [rows, cols], shift, codes, seen, plain),
                    _ => Vec::new(),
                };
                for &i in &piece {
                    let mut s = shifted_cell(i, shift, [rows, cols]);
                    if cut.get(s).copied().unwrap_or(false) {
                        // the row's nearest ground in the bank frame, else the object's cell
                        let (y, x) = (s / cols, s % cols);
                        let plain = plain.unwrap_or(&[]);
                        let ground =
                            (1..cols).flat_map(|d| [x.checked_sub(d), Some(x + d).filter(|&v| v < cols)]).find_map(
                                |v| v.filter(|&v| plain.get(grid[y * cols + v] as usize).copied().unwrap_or(false)),
                            );
                        if let Some(v) = ground {
                            s = y * cols + v;
                        }
                    }
                    codes[i] = grid[s] as u32;
                    sources.push([i, frame, s]);
                    pasted[i] = Some(Pasted { frame, cell: s, offset_px });
                    open[i] = false;
                }
                draws.push(BankDraw { frame, shift, score, cells: piece.len(), hole: holes, offset_px });
            }
            holes += 1;
        }
        BankFill { draws, deferred, sources }
    }

    /// The bank frame and shift one piece of a hole takes, and its score: the draw among the
    /// best matches of the known cells around the piece (`open`: cells without content yet;
    /// `pasted`: what the cells filled before took).
    #[allow(clippy::too_many_arguments)]
    fn draw_piece(
        &self,
        piece: &[usize],
        codes: &[u32],
        open: &[bool],
        pasted: &[Option<Pasted>],
        looks: &[[f32; 4]],
        hints: &FillHints<'_>,
        search: &BankSearch,
        rng: &mut impl Rng,
    ) -> (usize, [i32; 2], [i32; 2], f32) {
        let (rows, cols) = (self.rows, self.cols);
        let look = |c: u32| looks.get(c as usize).copied().unwrap_or([0.0; 4]);
        let band = border_band(piece, open, rows, cols, search.band);
        if band.is_empty() {
            return (rng.random_range(0..self.len()), [0, 0], [0, 0], f32::NAN);
        }
        // horizontal shifts that keep the piece inside the bank frame (a row fixes the
        // ground's planar depth, a column does not), at most `max_shift_x` either way
        let (x_lo, x_hi) = piece.iter().fold((cols as i32, 0), |(lo, hi), &i| {
            let x = (i % cols) as i32;
            (lo.min(x), hi.max(x))
        });
        let (dx_lo, dx_hi) = ((-x_lo).max(-search.max_shift_x), (cols as i32 - 1 - x_hi).min(search.max_shift_x));
        let shifts: Vec<[i32; 2]> = (-search.max_shift_y..=search.max_shift_y)
            .flat_map(|dy| (dx_lo.min(0)..=dx_hi.max(0)).map(move |dx| [dy, dx]))
            .collect();
        let query: Vec<(i32, i32, [f32; 4])> =
            band.iter().map(|&i| ((i / cols) as i32, (i % cols) as i32, look(codes[i]))).collect();
        let mut scored: Vec<Match> = (0..self.len())
            .into_par_iter()
            .flat_map_iter(|f| {
                let grid = self.frame(f);
                let query = &query;
                shifts.iter().map(move |&[dy, dx]| {
                    let mut s = 0.0f32;
                    for &(y, x, q) in query {
                        let (by, bx) = (y + dy, x + dx);
                        s += if by < 0 || bx < 0 || by >= rows as i32 || bx >= cols as i32 {
                            OUT_OF_FRAME
                        } else {
                            let b = look(grid[by as usize * cols + bx as usize] as u32);
                            (0..4).map(|k| (q[k] - b[k]).abs()).sum::<f32>()
                        };
                    }
                    (s / query.len() as f32, f, [dy, dx], [0, 0])
                })
            })
            .collect();
        if let Some(usable) = hints.source_usable {
            // a match that would take a cell with nothing whole behind it is passed over
            let whole = |c: &Match| piece.iter().all(|&i| usable(c.1, shifted_cell(i, c.2, [rows, cols])));
            if scored.iter().any(whole) {
                scored.retain(whole);
            }
        }
        if let Some(distance) = hints.band_distance {
            // the best matches by the codes' looks, ranked again by the band's pixels
            keep_best(&mut scored, PIXEL_CANDIDATES);
            let band_pasted: Vec<Option<Pasted>> = band.iter().map(|&i| pasted[i]).collect();
            scored.par_iter_mut().for_each(|c| c.0 = distance(c.1, c.2, [0, 0], &band, &band_pasted));
            let r = hints.pixel_offsets;
            if r > 0 {
                // the best of them also at every pixel offset within `r`: a band the camera
                // moved by part of a cell is continued in step, not by the nearest cell
                // (every second offset, then the 8 around the best of them)
                keep_best(&mut scored, OFFSET_CANDIDATES);
                let coarse: Vec<[i32; 2]> = (-r..=r)
                    .step_by(2)
                    .flat_map(|oy| (-r..=r).step_by(2).map(move |ox| [oy, ox]))
                    .filter(|o| *o != [0, 0])
                    .collect();
                scored.par_iter_mut().for_each(|c| {
                    let try_at = |c: &mut Match, o: [i32; 2]| {
                        let d = distance(c.1, c.2, o, &band, &band_pasted);
                        if d < c.0 {
                            (c.0, c.3) = (d, o);
                        }
                    };
                    for &o in &coarse {
                        try_at(c, o);
                    }
                    let [oy, ox] = c.3;
                    for o in [-1, 0, 1].into_iter().flat_map(|dy| [-1, 0, 1].map(|dx| [oy + dy, ox + dx])) {
                        if o != [oy, ox] && o[0].abs() <= r && o[1].abs() <= r {
                            try_at(c, o);
                        }
                    }
                });
            }
        }
        if let (Some(plain), true) = (hints.plain, search.whole_objects) {
            // of the best matches, those whose objects the piece would cut pay for it: the draw
            // prefers a placement whose objects fit the hole whole
            keep_best(&mut scored, CUT_CANDIDATES);
            for c in scored.iter_mut() {
                let cut = cut_objects(self.frame(c.1), [rows, cols], c.2, codes, open, plain);
                let n = piece.iter().filter(|&&i| cut[shifted_cell(i, c.2, [rows, cols])]).count();
                c.0 += CUT_PENALTY * n as f32 / piece.len() as f32;
            }
        }
        let k = search.top_k.clamp(1, scored.len());
        keep_best(&mut scored, k);
        scored.sort_by(by_score);
        // softmax over the k best by score, at temperature `search.tau`: a hole whose border
        // continues one bank frame (an object re-rendered from an earlier step) takes that
        // frame; a hole on plain ground draws among many near-equal matches
        let best = scored[0].0;
        let weights: Vec<f32> = scored[..k].iter().map(|c| (-(c.0 - best) / search.tau.max(1e-6)).exp()).collect();
        let total: f32 = weights.iter().sum();
        let mut u = rng.random_range(0.0..total.max(f32::MIN_POSITIVE));
        let mut pick = k - 1;
        for (j, w) in weights.iter().enumerate() {
            if u < *w {
                pick = j;
                break;
            }
            u -= w;
        }
        let (s, f, shift, offset) = scored[pick];
        (f, shift, offset, s)
    }
}

/// A match: its score, the bank frame, the shift in cells, the pixel offset.
type Match = (f32, usize, [i32; 2], [i32; 2]);

/// A match's order: lower score first, then the lower frame (a deterministic order for ties).
fn by_score(a: &Match, b: &Match) -> std::cmp::Ordering {
    a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
}

/// Keeps the `n` best of `scored` (in no particular order).
fn keep_best(scored: &mut Vec<Match>, n: usize) {
    let n = n.clamp(1, scored.len().max(1));
    if scored.len() > n {
        scored.select_nth_unstable_by(n - 1, by_score);
        scored.truncate(n);
    }
}

/// The cell of a bank frame placed with `shift` under cell `i` of the frame (clamped to the
/// bank frame).
fn shifted_cell(i: usize, shift: [i32; 2], [rows, cols]: [usize; 2]) -> usize {
    let y = ((i / cols) as i32 + shift[0]).clamp(0, rows as i32 - 1) as usize;
    let x = ((i % cols) as i32 + shift[1]).clamp(0, cols as i32 - 1) as usize;
    y * cols + x
}

/// Per cell of a bank frame `grid` placed with `shift` over a frame whose observed cells hold
/// `codes`: whether it belongs to an object (a 4-connected group of cells whose codes are not
/// `plain`) that an observed plain cell of the frame would cut, i.e. one of the object's cells
/// lands on observed ground. Objects that land only on missing cells, on observed objects (they
/// continue one) or outside the frame are whole and kept.
fn cut_objects(
    grid: &[u16],
    [rows, cols]: [usize; 2],
    shift: [i32; 2],
    codes: &[u32],
    missing: &[bool],
    plain: &[bool],
) -> Vec<bool> {
    let is_plain = |c: u32| plain.get(c as usize).copied().unwrap_or(true);
    let coloured: Vec<bool> = grid.iter().map(|&c| !is_plain(c as u32)).collect();
    let mut cut = vec![false; rows * cols];
    for object in components(&coloured, rows, cols) {
        let on_ground = object.iter().any(|&b| {
            let (y, x) = ((b / cols) as i32 - shift[0], (b % cols) as i32 - shift[1]);
            if y < 0 || x < 0 || y >= rows as i32 || x >= cols as i32 {
                return false;
            }
            let t = y as usize * cols + x as usize;
            !missing[t] && is_plain(codes[t])
        });
        if on_ground {
            for &b in &object {
                cut[b] = true;
            }
        }
    }
    cut
}

/// What [`CodeBank::fill_with`] may know besides the codes.
#[derive(Default, Clone, Copy)]
pub struct FillHints<'a> {
    /// Which codes are plain ground (`plain[code]`), for [`BankSearch::whole_objects`].
    pub plain: Option<&'a [bool]>,
    /// The distance between a hole's border band (its cells) and bank frame `frame` shifted by
    /// `shift`, measured on pixels (a seed's bank, whose pixels are known): the best matches by
    /// the codes' looks are ranked again by it, as image quilting matches the overlap's pixels.
    /// Its arguments: the bank frame, the shift, a pixel offset (the source's pixels are taken
    /// that many pixels `[down, right]` of its cells), the band's cells and, per band cell,
    /// what a tile filled before took there ([`BankSearch::tile`]): its pixels are those of
    /// that source.
    #[allow(clippy::type_complexity)]
    pub band_distance: Option<&'a (dyn Fn(usize, [i32; 2], [i32; 2], &[usize], &[Option<Pasted>]) -> f32 + Sync)>,
    /// With `band_distance`: the best matches are tried at every pixel offset up to this many
    /// pixels each way (0: none).
    pub pixel_offsets: i32,
    /// Whether cell `cell` of bank frame `frame` may give its content to a hole (a seed's bank:
    /// its pixels are all there, [`BankPixels::complete_cells`]). A match that would take any of
    /// its hole's cells from an unusable one is passed over, unless every match would.
    pub source_usable: Option<&'a (dyn Fn(usize, usize) -> bool + Sync)>,
    /// Per cell, what an earlier fill of the same frame put there ([`BankFill::pasted`]): a band
    /// cell with a source has that source's pixels for `band_distance`.
    pub filled: Option<&'a [Option<Pasted>]>,
}

impl std::fmt::Debug for FillHints<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FillHints")
            .field("plain", &self.plain.map(<[bool]>::len))
            .field("band_distance", &self.band_distance.is_some())
            .field("source_usable", &self.source_usable.is_some())
            .field("filled", &self.filled.map(<[Option<Pasted>]>::len))
            .finish()
    }
}

/// With [`FillHints::pixel_offsets`]: how many of the best matches by pixels are tried at
/// pixel offsets.
const OFFSET_CANDIDATES: usize = 8;

/// With [`FillHints::band_distance`]: how many of the best matches by looks are ranked again.
const PIXEL_CANDIDATES: usize = 64;

/// With [`BankSearch::whole_objects`]: how many of the best matches are scored for the objects
/// they would cut ...
const CUT_CANDIDATES: usize = 64;
/// ... and what a hole whose every cell belongs to a cut object adds to a match's score (a
/// band's descriptor distance is 0.05-0.3; the draw's temperature 0.02).
const CUT_PENALTY: f32 = 0.2;

/// Descriptor distance charged for a band cell that a shift moves out of the bank frame.
const OUT_OF_FRAME: f32 = 1.0;

/// The cells of the holes of `missing` (4-connected, `rows x cols` cells) that touch a side of
/// the frame and reach fewer than `thinner_than` cells in from it: the bands that wait
/// ([`crate::RefinerOptions::bands_wait`]), in ascending order.
pub fn thin_border_bands(missing: &[bool], rows: usize, cols: usize, thinner_than: usize) -> Vec<usize> {
    let mut out: Vec<usize> = components(missing, rows, cols)
        .into_iter()
        .filter(|hole| thin_at_border(hole, rows, cols, thinner_than))
        .flatten()
        .collect();
    out.sort_unstable();
    out
}

/// Whether `hole` touches a side of the frame and reaches fewer than `thinner_than` cells in
/// from it.
fn thin_at_border(hole: &[usize], rows: usize, cols: usize, thinner_than: usize) -> bool {
    let (mut y0, mut y1, mut x0, mut x1) = (rows, 0, cols, 0);
    for &i in hole {
        let (y, x) = (i / cols, i % cols);
        (y0, y1, x0, x1) = (y0.min(y), y1.max(y), x0.min(x), x1.max(x));
    }
    let (tall, wide) = (y1 + 1 - y0, x1 + 1 - x0);
    let (at_side, at_top_or_bottom) = (x0 == 0 || x1 + 1 == cols, y0 == 0 || y1 + 1 == rows);
    (at_side && wide < thinner_than) || (at_top_or_bottom && tall < thinner_than)
}

/// Per cell: whether it belongs to a run of `missing` cells that starts at a side of the frame
/// (along its row from the left or right side, along its column from the top or bottom) and
/// is shorter than `thinner_than`, or to a group of missing cells left over by those runs
/// that lies within `thinner_than - 1` cells of the sides (where two bands meet).
fn border_runs(missing: &[bool], rows: usize, cols: usize, thinner_than: usize) -> Vec<bool> {
    let mut out = vec![false; rows * cols];
    let mut mark = |cells: &mut dyn Iterator<Item = usize>| {
        let run: Vec<usize> = cells.take_while(|&i| missing[i]).take(thinner_than).collect();
        if run.len() < thinner_than {
            for i in run {
                out[i] = true;
            }
        }
    };
    for y in 0..rows {
        mark(&mut (0..cols).map(|x| y * cols + x));
        mark(&mut (0..cols).rev().map(|x| y * cols + x));
    }
    for x in 0..cols {
        mark(&mut (0..rows).map(|y| y * cols + x));
        mark(&mut (0..rows).rev().map(|y| y * cols + x));
    }
    // what is left of the runs where two bands meet (a corner's cells, whose row and column
    // are both long runs) waits with them: a piece no deeper than such bands are, at a side or
    // beside a run that waits (a crack near a side that touches neither is filled)
    let rest: Vec<bool> = missing.iter().zip(&out).map(|(m, o)| *m && !o).collect();
    for piece in components(&rest, rows, cols) {
        let side = |y: usize, x: usize| y.min(rows - 1 - y).min(x).min(cols - 1 - x);
        let near = piece.iter().all(|&i| side(i / cols, i % cols) + 1 < thinner_than);
        let joined = piece.iter().any(|&i| {
            let (y, x) = (i / cols, i % cols);
            side(y, x) == 0
                || (y > 0 && out[i - cols])
                || (y + 1 < rows && out[i + cols])
                || (x > 0 && out[i - 1])
                || (x + 1 < cols && out[i + 1])
        });
        if near && joined {
            for i in piece {
                out[i] = true;
            }
        }
    }
    out
}

/// The 4-connected components of `missing`, each as its cells in ascending order, ordered by
/// their first cell.
pub fn components(missing: &[bool], rows: usize, cols: usize) -> Vec<Vec<usize>> {
    let mut seen = vec![false; missing.len()];
    let mut out = Vec::new();
    for start in 0..missing.len() {
        if !missing[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let (mut stack, mut cells) = (vec![start], Vec::new());
        while let Some(i) = stack.pop() {
            cells.push(i);
            let (y, x) = (i / cols, i % cols);
            let mut visit = |j: usize| {
                if missing[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if y > 0 {
                visit(i - cols);
            }
            if y + 1 < rows {
                visit(i + cols);
            }
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < cols {
                visit(i + 1);
            }
        }
        cells.sort_unstable();
        out.push(cells);
    }
    out
}

/// `hole` (cells of a `cols`-wide grid) cut into `tile x tile` tiles from its bounding box's
/// corner, in reading order; the whole hole when `tile` is 0 or it fits one tile.
fn tiles(hole: &[usize], cols: usize, tile: usize) -> Vec<Vec<usize>> {
    if tile == 0 || hole.len() <= tile * tile {
        return vec![hole.to_vec()];
    }
    let (y0, x0) = hole.iter().fold((usize::MAX, usize::MAX), |(y, x), &i| (y.min(i / cols), x.min(i % cols)));
    let mut by_tile: std::collections::BTreeMap<(usize, usize), Vec<usize>> = Default::default();
    for &i in hole {
        by_tile.entry(((i / cols - y0) / tile, (i % cols - x0) / tile)).or_default().push(i);
    }
    by_tile.into_values().collect()
}

/// How many cells lie within `width` cells (Chebyshev) of `piece` and outside it: the band
/// [`border_band`] gives when every one of them is visible.
fn band_cells(piece: &[usize], rows: usize, cols: usize, width: usize) -> usize {
    let mut inside = vec![false; rows * cols];
    for &i in piece {
        inside[i] = true;
    }
    border_band(piece, &inside, rows, cols, width).len()
}

/// The visible cells within `width` cells (Chebyshev) of `hole`, ascending.
fn border_band(hole: &[usize], missing: &[bool], rows: usize, cols: usize, width: usize) -> Vec<usize> {
    let mut in_band = vec![false; missing.len()];
    let w = width as i64;
    for &i in hole {
        let (y, x) = ((i / cols) as i64, (i % cols) as i64);
        for yy in (y - w).max(0)..=(y + w).min(rows as i64 - 1) {
            for xx in (x - w).max(0)..=(x + w).min(cols as i64 - 1) {
                let j = yy as usize * cols + xx as usize;
                if !missing[j] {
                    in_band[j] = true;
                }
            }
        }
    }
    (0..missing.len()).filter(|&j| in_band[j]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn looks(n: usize) -> Vec<[f32; 4]> {
        (0..n).map(|c| [c as f32 / n as f32, 0.0, 0.0, 0.0]).collect()
    }

    #[test]
    fn bytes_round_trip_and_damage_is_refused() {
        let bank = CodeBank {
            rows: 2,
            cols: 3,
            n_embed: 10,
            codebook_crc32: 7,
            codes: vec![1, 2, 3, 4, 5, 6, 9, 8, 7, 6, 5, 4],
        };
        let bytes = bank.to_bytes();
        assert_eq!(CodeBank::from_bytes(&bytes).unwrap(), bank);
        let mut bad = bytes.clone();
        bad[30] ^= 1;
        assert!(CodeBank::from_bytes(&bad).unwrap_err().to_string().contains("checksum"));
        assert!(CodeBank::from_bytes(&bytes[..bytes.len() - 2]).is_err());
        let big = CodeBank { n_embed: 5, ..bank };
        assert!(CodeBank::from_bytes(&big.to_bytes()).unwrap_err().to_string().contains("outside"));
    }

    #[test]
    fn whole_objects_leave_out_an_object_that_observed_ground_would_cut_and_keep_the_rest() {
        // one bank frame, 8 x 8, ground code 0 (plain), objects: code 1 at (2..4, 1..3), code 2
        // at (5, 5..7), code 3 at (0, 6); codes 1-3 are coloured
        let (rows, cols) = (8usize, 8usize);
        let n = rows * cols;
        let mut grid = vec![0u16; n];
        for (y, x, c) in [(2, 1, 1), (2, 2, 1), (3, 1, 1), (3, 2, 1), (5, 5, 2), (5, 6, 2), (0, 6, 3)] {
            grid[y * cols + x] = c;
        }
        let bank = CodeBank { rows, cols, n_embed: 8, codebook_crc32: 0, codes: grid.clone() };
        let plain = [true, false, false, false, true, true, true, true];
        // the frame: ground everywhere (code 4, plain) but an observed object (code 3) at (0, 6)
        let mut codes = vec![4u32; n];
        codes[6] = 3;
        // the hole: rows 2..6, columns 2..8 — object 1 is half in it (column 1 is observed
        // ground), object 2 wholly in it; object 3 lies on the observed object cell
        let mut missing = vec![false; n];
        for y in 2..6 {
            for x in 2..8 {
                missing[y * cols + x] = true;
            }
        }
        missing[6] = false;
        let search = BankSearch { top_k: 1, max_shift_x: 0, max_shift_y: 0, min_cells: 1, ..Default::default() };
        let fill = |whole: bool| {
            let mut c = codes.clone();
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let s = BankSearch { whole_objects: whole, ..search };
            bank.fill_with(
                &mut c,
                &missing,
                &looks(8),
                &FillHints { plain: Some(&plain), ..Default::default() },
                &s,
                &mut rng,
            );
            c
        };
        let cut = fill(false);
        let whole = fill(true);
        // without the rule the hole takes object 1's right half: a fragment
        assert_eq!((cut[2 * cols + 2], cut[3 * cols + 2]), (1, 1));
        // with it, that half is the row's ground, and the whole object 2 stays
        assert!(plain[whole[2 * cols + 2] as usize] && plain[whole[3 * cols + 2] as usize], "{whole:?}");
        assert_eq!((whole[5 * cols + 5], whole[5 * cols + 6]), (2, 2));
        // every other hole cell is as without the rule
        for i in (0..n).filter(|&i| missing[i] && ![2 * cols + 2, 3 * cols + 2].contains(&i)) {
            assert_eq!(whole[i], cut[i], "cell {i}");
        }
        // observed cells are never written
        for i in (0..n).filter(|&i| !missing[i]) {
            assert_eq!(whole[i], codes[i], "cell {i}");
        }
        // an object that continues an observed object is kept: object 3 lands on the observed
        // object cell (0, 6) and the cell below it is in a hole
        let mut m2 = vec![false; n];
        m2[cols + 6] = true;
        let mut grid3 = vec![0u16; n];
        grid3[6] = 3;
        grid3[cols + 6] = 3;
        let bank3 = CodeBank { rows, cols, n_embed: 8, codebook_crc32: 0, codes: grid3 };
        let mut c = codes.clone();
        let s = BankSearch { whole_objects: true, ..search };
        let hints = FillHints { plain: Some(&plain), ..Default::default() };
        bank3.fill_with(&mut c, &m2, &looks(8), &hints, &s, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(c[cols + 6], 3);
    }

    #[test]
    fn a_band_distance_on_pixels_decides_between_frames_whose_codes_look_alike() {
        let (rows, cols) = (6usize, 6usize);
        let n = rows * cols;
        // two bank frames with the same codes: the looks cannot tell them apart
        let f: Vec<u16> = (0..n as u16).collect();
        let bank = CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: [f.clone(), f.clone()].concat() };
        let mut missing = vec![false; n];
        for i in [14, 15, 20, 21] {
            missing[i] = true;
        }
        // the pixels say frame 1 continues the band, frame 0 does not
        let distance =
            |frame: usize, _shift: [i32; 2], _offset: [i32; 2], band: &[usize], _pasted: &[Option<Pasted>]| {
                assert!(!band.is_empty() && band.iter().all(|&c| !missing[c]));
                if frame == 1 {
                    0.0
                } else {
                    0.5
                }
            };
        let hints = FillHints { band_distance: Some(&distance), ..Default::default() };
        let search = BankSearch { min_cells: 1, ..Default::default() };
        for seed in 0..16 {
            let mut codes: Vec<u32> = f.iter().map(|&c| c as u32).collect();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let fill = bank.fill_with(&mut codes, &missing, &looks(64), &hints, &search, &mut rng);
            assert_eq!(fill.draws.len(), 1);
            assert_eq!(fill.draws[0].frame, 1, "seed {seed}: {:?}", fill.draws);
            assert_eq!(fill.draws[0].score, 0.0);
        }
        // without it, both frames are drawn
        let frames: std::collections::HashSet<usize> = (0..16)
            .map(|seed| {
                let mut codes: Vec<u32> = f.iter().map(|&c| c as u32).collect();
                bank.fill(&mut codes, &missing, &looks(64), &search, &mut ChaCha8Rng::seed_from_u64(seed)).draws[0]
                    .frame
            })
            .collect();
        assert_eq!(frames.len(), 2);
    }

    #[test]
    fn a_match_whose_source_cells_lack_pixels_is_passed_over_unless_every_match_would_take_them() {
        let (rows, cols) = (6usize, 6usize);
        let n = rows * cols;
        let f0: Vec<u16> = (0..n as u16).collect();
        // frame 0 matches the band exactly; frame 1 is one code off everywhere
        let f1: Vec<u16> = f0.iter().map(|c| c + 1).collect();
        let bank = CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: [f0.clone(), f1].concat() };
        let mut missing = vec![false; n];
        for i in [14, 15, 20, 21] {
            missing[i] = true;
        }
        let search = BankSearch { top_k: 1, max_shift_x: 0, max_shift_y: 0, min_cells: 1, ..Default::default() };
        let draw = |usable: &(dyn Fn(usize, usize) -> bool + Sync)| {
            let mut codes: Vec<u32> = f0.iter().map(|&c| c as u32).collect();
            let hints = FillHints { source_usable: Some(usable), ..Default::default() };
            let mut rng = ChaCha8Rng::seed_from_u64(1);
            bank.fill_with(&mut codes, &missing, &looks(64), &hints, &search, &mut rng).draws[0].frame
        };
        assert_eq!(draw(&|_, _| true), 0);
        // frame 0 has nothing behind cell 20 (the hole's own place, say): frame 1 it is
        assert_eq!(draw(&|frame, cell| !(frame == 0 && cell == 20)), 1);
        // a cell outside the hole does not matter
        assert_eq!(draw(&|frame, cell| !(frame == 0 && cell == 0)), 0);
        // when no match is whole the best one is still taken
        assert_eq!(draw(&|_, cell| cell != 20), 0);
    }

    #[test]
    fn complete_cells_are_those_with_every_pixel_s_depth() {
        let bank = CodeBank { rows: 2, cols: 2, n_embed: 4, codebook_crc32: 0, codes: vec![0; 4] };
        let mut frame = sgam_core::RgbdFrame::empty(4, 4);
        frame.depth_m.data.iter_mut().for_each(|d| *d = 2.0);
        frame.depth_m.data[2 * 4 + 3] = 0.0; // a pixel of cell (1, 1)
        let pixels = BankPixels { bases: vec![frame], roll_cells: [0, 0] };
        assert_eq!(pixels.complete_cells(&bank, 2), vec![vec![true, true, true, false]]);
        assert_eq!(pixels.source_index(&bank, 0, 3), Some((0, [1, 1])));
        assert_eq!(pixels.source_index(&bank, 1, 3), None);
    }

    #[test]
    fn components_are_four_connected() {
        // x . x
        // x . .
        // . . x   -> holes {0, 3}, {2}, {8}
        let m = [true, false, true, true, false, false, false, false, true];
        assert_eq!(components(&m, 3, 3), vec![vec![0, 3], vec![2], vec![8]]);
    }

    /// The hole takes the frame whose border matches, and its codes are that frame's, shifted.
    #[test]
    fn a_hole_takes_the_matching_frame() {
        let (rows, cols) = (6usize, 6usize);
        let n = rows * cols;
        // frame 0: codes 0..36; frame 1: the same shifted right by one column (code of cell
        // (y, x) = y * 6 + x - 1); frame 2: constant 35
        let f0: Vec<u16> = (0..n as u16).collect();
        let f1: Vec<u16> = (0..n).map(|i| (i as i32 - 1).max(0) as u16).collect();
        let f2 = vec![35u16; n];
        let bank = CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: [f0.clone(), f1, f2].concat() };
        let mut codes: Vec<u32> = f0.iter().map(|&c| c as u32).collect();
        let mut missing = vec![false; n];
        for i in [14, 15, 20, 21] {
            missing[i] = true;
            codes[i] = 63;
        }
        let search = BankSearch { top_k: 1, max_shift_y: 0, min_cells: 1, ..Default::default() };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let draws = bank.fill(&mut codes, &missing, &looks(64), &search, &mut rng).draws;
        assert_eq!(draws.len(), 1);
        assert_eq!(draws[0].cells, 4);
        assert!(draws[0].score < 1e-6, "{draws:?}");
        // frame 0 unshifted or frame 1 shifted by +1 column match exactly; both give 0..36 back
        for (i, c) in codes.iter().enumerate() {
            assert_eq!(*c, i as u32, "cell {i}: {draws:?}");
        }
    }

    #[test]
    fn top_k_gives_variety_and_a_seed_repeats() {
        let (rows, cols) = (4usize, 4usize);
        let frames: Vec<u16> = (0..8u16).flat_map(|f| std::iter::repeat_n(f, rows * cols)).collect();
        let bank = CodeBank { rows, cols, n_embed: 8, codebook_crc32: 0, codes: frames };
        let missing: Vec<bool> = (0..16).map(|i| i == 5 || i == 6).collect();
        let search =
            BankSearch { top_k: 8, tau: 100.0, min_cells: 1, max_shift_x: 0, max_shift_y: 0, ..Default::default() };
        let draw = |seed: u64| {
            let mut codes = vec![0u32; 16];
            bank.fill(&mut codes, &missing, &looks(8), &search, &mut ChaCha8Rng::seed_from_u64(seed)).draws[0].frame
        };
        let seen: std::collections::HashSet<usize> = (0..40).map(draw).collect();
        assert!(seen.len() >= 4, "{seen:?}");
        assert_eq!(draw(7), draw(7));
    }

    #[test]
    fn tiles_cut_a_hole_from_its_corner_and_cover_it_once() {
        let cols = 10;
        let hole: Vec<usize> = (2..5).flat_map(|y| (1..10).map(move |x| y * cols + x)).collect();
        let pieces = tiles(&hole, cols, 4);
        assert_eq!(pieces.iter().map(Vec::len).collect::<Vec<_>>(), [12, 12, 3]);
        let mut all: Vec<usize> = pieces.concat();
        all.sort_unstable();
        assert_eq!(all, hole);
        for p in &pieces {
            let xs: Vec<usize> = p.iter().map(|i| i % cols).collect();
            assert!(xs.iter().max().unwrap() - xs.iter().min().unwrap() < 4, "{p:?}");
        }
        assert_eq!(tiles(&hole, cols, 0), vec![hole.clone()]);
        assert_eq!(tiles(&hole[..16], cols, 4), [hole[..16].to_vec()]);
    }

    #[test]
    fn runs_from_the_sides_shorter_than_the_limit_wait_and_no_other_cell() {
        let (rows, cols) = (8usize, 8usize);
        let mut missing = vec![false; rows * cols];
        for y in 0..rows {
            missing[y * cols + 6] = true;
            missing[y * cols + 7] = true;
        }
        // a crack from the band into the frame along row 4, and a run of 3 from the left side
        for x in 2..6 {
            missing[4 * cols + x] = true;
        }
        for x in 0..3 {
            missing[2 * cols + x] = true;
        }
        let runs = border_runs(&missing, rows, cols, 3);
        let marked: Vec<usize> = (0..rows * cols).filter(|&i| runs[i]).collect();
        // the corner where a top row band meets the right band waits with them
        let mut l = vec![false; rows * cols];
        for i in 0..rows * cols {
            l[i] = i % cols == cols - 1 || i / cols == 0;
        }
        assert!(border_runs(&l, rows, cols, 3).iter().zip(&l).all(|(r, m)| r == m));
        // a crack one cell in from a side, touching neither the side nor a run, is filled
        let mut crack = vec![false; rows * cols];
        crack[cols + 3] = true;
        assert!(!border_runs(&crack, rows, cols, 3)[cols + 3]);
        let expected: Vec<usize> = (0..rows).filter(|&y| y != 4).flat_map(|y| [y * cols + 6, y * cols + 7]).collect();
        assert_eq!(marked, expected);
        // in the bank's fill they wait, and the crack (with the band's cells on its row) is filled
        let bank = CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: (0..64u16).collect() };
        let search = BankSearch { defer_runs: true, min_cells: 1, ..Default::default() };
        let mut codes = vec![0u32; rows * cols];
        let fill = bank.fill(&mut codes, &missing, &looks(64), &search, &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(fill.deferred, expected);
        let filled: usize = fill.draws.iter().map(|d| d.cells).sum();
        assert_eq!(filled, missing.iter().filter(|m| **m).count() - expected.len());
    }

    #[test]
    fn a_band_quilted_as_tiles_continues_each_tiles_own_neighbours() {
        let (rows, cols) = (8usize, 8usize);
        let n = rows * cols;
        // bank frame 0: code 1 above, 7 below; frame 1: code 3 above, 2 below. As one piece the
        // band's border (1 above, 2 below) is nearer frame 1; as tiles, the top tile's border
        // is mostly frame 0's, the bottom tile's (with the top tile's cells) frame 1's
        let half = |top: u16, bottom: u16| (0..n).map(move |i| if i / cols < 4 { top } else { bottom });
        let bank =
            CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: half(1, 7).chain(half(3, 2)).collect() };
        // the frame: 1 above, 2 below, its three right columns missing
        let missing: Vec<bool> = (0..n).map(|i| i % cols >= 5).collect();
        let fresh = || -> Vec<u32> { half(1, 2).map(u32::from).collect() };
        let search = BankSearch {
            band: 1,
            top_k: 1,
            max_shift_x: 0,
            max_shift_y: 0,
            min_cells: 1,
            defer_thinner_than: 0,
            tile: 4,
            ..Default::default()
        };
        let mut codes = fresh();
        let fill = bank.fill(&mut codes, &missing, &looks(64), &search, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(fill.draws.iter().map(|d| (d.frame, d.cells, d.hole)).collect::<Vec<_>>(), [(0, 12, 0), (1, 12, 0)]);
        assert_eq!(codes, fresh(), "every tile takes what continues its neighbours");
        // in one piece, the hole takes one frame and half of it is wrong
        let mut codes = fresh();
        let fill = bank.fill(
            &mut codes,
            &missing,
            &looks(64),
            &BankSearch { tile: 0, ..search },
            &mut ChaCha8Rng::seed_from_u64(3),
        );
        assert_eq!(fill.draws.len(), 1);
        assert_eq!(codes.iter().zip(fresh()).filter(|(a, b)| **a != *b).count(), 12);
    }

    #[test]
    fn a_tiles_band_distance_sees_what_the_tiles_before_it_took() {
        let (rows, cols) = (8usize, 8usize);
        let bank =
            CodeBank { rows, cols, n_embed: 64, codebook_crc32: 0, codes: (0..2 * 64u16).map(|c| c % 64).collect() };
        let missing: Vec<bool> = (0..rows * cols).map(|i| i % cols >= 5).collect();
        let calls = std::sync::Mutex::new(Vec::new());
        let distance =
            |frame: usize, _shift: [i32; 2], _offset: [i32; 2], band: &[usize], pasted: &[Option<Pasted>]| {
                assert_eq!(band.len(), pasted.len());
                calls.lock().unwrap().push((band.to_vec(), pasted.to_vec()));
                frame as f32
            };
        let hints = FillHints { band_distance: Some(&distance), ..Default::default() };
        let search =
            BankSearch { band: 1, top_k: 1, min_cells: 1, defer_thinner_than: 0, tile: 4, ..Default::default() };
        let mut codes: Vec<u32> = (0..64).collect();
        let fill = bank.fill_with(&mut codes, &missing, &looks(64), &hints, &search, &mut ChaCha8Rng::seed_from_u64(5));
        assert_eq!(fill.draws.len(), 2);
        let first = fill.draws[0];
        let calls = calls.into_inner().unwrap();
        let mut saw_pasted = false;
        for (band, pasted) in &calls {
            for (cell, p) in band.iter().zip(pasted) {
                match p {
                    Some(p) => {
                        assert!(missing[*cell], "cell {cell} was observed");
                        assert_eq!((p.frame, p.offset_px), (first.frame, first.offset_px));
                        assert_eq!(p.cell, shifted_cell(*cell, first.shift, [rows, cols]));
                        saw_pasted = true;
                    }
                    None => assert!(!missing[*cell], "cell {cell}: filled before, but no source"),
                }
            }
        }
        assert!(saw_pasted, "the second tile's band holds the first tile's cells");
    }
}
