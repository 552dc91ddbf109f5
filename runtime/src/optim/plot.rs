//! Optimization-history figures (loss, parameters, gradients over iterations)
//! written as PNG and SVG with `plotters`.
//!
//! Text in the PNG is rasterised by plotters' `ab_glyph` feature from an
//! embedded DejaVu Sans (no fontconfig/freetype). The font is registered once
//! per process under plotters' "sans-serif" family. The SVG refers to the
//! generic "sans-serif" family and doesn't embed the font.
//!
//! Layout: the panels are stacked vertically and share one x axis
//! ("iteration", index into `Series::values`); each panel has a legend column
//! on its right, so the plot areas line up and legends never hide data.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

use plotters::coord::Shift;
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{FontStyle, register_font};

/// DejaVu Sans 2.37 (Bitstream Vera / Arev licence, see `DejaVuSans-LICENSE.txt`
/// next to it). Adjust the path when moving this file.
static FONT_TTF: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");

/// One curve: one value per iteration (index = iteration, from 0).
/// NaN (or any non-finite value) = missing point.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Series {
    pub label: String,
    pub values: Vec<f64>,
}

/// One stacked sub-plot.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Panel {
    pub title: String,
    pub y_label: String,
    /// Logarithmic y axis. Values <= 0 are skipped; a panel without any
    /// positive value falls back to a linear axis.
    pub log_y: bool,
    pub series: Vec<Series>,
}

const WIDTH: u32 = 900;
const PANEL_HEIGHT: u32 = 300;
const TITLE_HEIGHT: u32 = 40;
const LEGEND_WIDTH: u32 = 170;
const LEGEND_LINE: i32 = 17;
const LEGEND_TOP: i32 = 40;
const LEGEND_MAX_CHARS: usize = 22;
const MAX_PANELS: usize = 64;
/// Draw a marker on every point when there are at most this many iterations
/// (otherwise only on isolated points, i.e. with missing neighbours).
const MARKERS_UP_TO: usize = 60;
const FONT_FAMILY: &str = "sans-serif";

/// tab10; series 10..19 reuse the colours dashed, and so on.
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// Writes `<stem>.png` and `<stem>.svg`: the panels stacked vertically, shared
/// x axis "iteration". Returns the two paths (PNG first). Each file is written
/// to a temporary file in the same folder and renamed into place. The folder
/// is created when missing.
pub fn write_figure(stem: &Path, title: &str, panels: &[Panel]) -> Result<Vec<PathBuf>, String> {
    if panels.is_empty() {
        return Err("plot: write_figure needs at least one panel".into());
    }
    if panels.len() > MAX_PANELS {
        return Err(format!(
            "plot: {} panels requested, at most {MAX_PANELS} supported",
            panels.len()
        ));
    }
    write_chart(stem, &Figure::prepare(title, panels))
}

/// What a figure file holds: its pixel size and how to draw it on any backend.
trait Chart {
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>;
}

/// Writes `<stem>.png` and `<stem>.svg` of a chart, each atomically (temporary file, rename).
fn write_chart(stem: &Path, fig: &impl Chart) -> Result<Vec<PathBuf>, String> {
    let file_name = stem
        .file_name()
        .ok_or_else(|| format!("plot: figure stem {} has no file name", stem.display()))?;
    ensure_font()?;

    let png_path = with_suffix(stem, ".png");
    let svg_path = with_suffix(stem, ".svg");
    let dir = match stem.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir)
        .map_err(|e| format!("plot: cannot create folder {}: {e}", dir.display()))?;

    let size = fig.size();

    // SVG: render into a string, then write it atomically.
    let mut svg_text = String::new();
    guarded("SVG", || {
        let root = SVGBackend::with_string(&mut svg_text, size).into_drawing_area();
        fig.draw(&root)?;
        root.present().map_err(|e| format!("finishing SVG: {e}"))
    })?;
    write_atomic(&svg_path, &dir, file_name, svg_text.as_bytes())?;

    // PNG: plotters' encoder picks the format from the extension, so the
    // temporary name ends in ".png" too.
    let tmp = temp_path(&dir, file_name, ".png", ".png");
    let drawn = guarded("PNG", || {
        let root = BitMapBackend::new(&tmp, size).into_drawing_area();
        fig.draw(&root)?;
        root.present()
            .map_err(|e| format!("encoding PNG {}: {e}", tmp.display()))
    });
    let finished = drawn.and_then(|()| {
        sync_file(&tmp)?;
        std::fs::rename(&tmp, &png_path).map_err(|e| {
            format!(
                "plot: cannot rename {} to {}: {e}",
                tmp.display(),
                png_path.display()
            )
        })
    });
    if let Err(e) = finished {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    Ok(vec![png_path, svg_path])
}

fn ensure_font() -> Result<(), String> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            register_font(FONT_FAMILY, FontStyle::Normal, FONT_TTF)
                .map_err(|_| "plot: the embedded font could not be parsed".to_string())
        })
        .clone()
}

/// Runs `f`, turning a panic inside plotters into an error.
fn guarded(what: &str, f: impl FnOnce() -> Result<(), String>) -> Result<(), String> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(format!("plot: drawing {what}: {e}")),
        Err(payload) => {
            let msg = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(format!("plot: drawing {what} panicked: {msg}"))
        }
    }
}

fn with_suffix(stem: &Path, suffix: &str) -> PathBuf {
    let mut s = stem.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// `<dir>/<name><ext>.tmp-<pid>-<n><tail>`
fn temp_path(dir: &Path, name: &std::ffi::OsStr, ext: &str, tail: &str) -> PathBuf {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let mut s = name.to_owned();
    s.push(format!("{ext}.tmp-{}-{n}{tail}", std::process::id()));
    dir.join(s)
}

fn sync_file(path: &Path) -> Result<(), String> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| format!("plot: cannot sync {}: {e}", path.display()))
}

fn write_atomic(
    dest: &Path,
    dir: &Path,
    name: &std::ffi::OsStr,
    bytes: &[u8],
) -> Result<(), String> {
    use std::io::Write;
    let tmp = temp_path(dir, name, ".svg", "");
    let res = std::fs::File::create(&tmp)
        .and_then(|mut f| {
            f.write_all(bytes)?;
            f.sync_all()
        })
        .map_err(|e| format!("plot: cannot write {}: {e}", tmp.display()))
        .and_then(|()| {
            std::fs::rename(&tmp, dest).map_err(|e| {
                format!(
                    "plot: cannot rename {} to {}: {e}",
                    tmp.display(),
                    dest.display()
                )
            })
        });
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res
}

// ---------------------------------------------------------------------------
// Data preparation (independent of the backend)

struct Figure {
    title: String,
    /// Last iteration index over all panels (shared x axis).
    last_iter: usize,
    markers: bool,
    panels: Vec<PreparedPanel>,
}

struct PreparedPanel {
    caption: String,
    y_label: String,
    /// `None`: nothing to plot ("no data" frame).
    axis: Option<YAxis>,
    series: Vec<PreparedSeries>,
}

struct PreparedSeries {
    label: String,
    /// Runs of consecutive drawable points, y already in axis space
    /// (log10 of the value on log axes).
    segments: Vec<Vec<(f64, f64)>>,
}

#[derive(Clone, Copy, PartialEq)]
enum YScale {
    Linear,
    Log10,
}

struct YAxis {
    scale: YScale,
    /// Axis-space range (log10 units on a log axis).
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
    minor: Vec<f64>,
    /// Label resolution for linear-valued labels (0 = per-value decade labels).
    step: f64,
    /// max(|lo|, |hi|) in value space, picks plain vs. scientific notation.
    magnitude: f64,
}

impl Figure {
    fn prepare(title: &str, panels: &[Panel]) -> Figure {
        let n_iter = panels
            .iter()
            .flat_map(|p| p.series.iter())
            .map(|s| s.values.len())
            .max()
            .unwrap_or(0);
        Figure {
            title: title.to_string(),
            last_iter: n_iter.saturating_sub(1),
            markers: n_iter <= MARKERS_UP_TO,
            panels: panels.iter().map(PreparedPanel::prepare).collect(),
        }
    }
}

impl Chart for Figure {
    fn size(&self) -> (u32, u32) {
        let title = if self.title.is_empty() {
            0
        } else {
            TITLE_HEIGHT
        };
        (WIDTH, title + PANEL_HEIGHT * self.panels.len() as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        root.fill(&WHITE).map_err(|e| format!("background: {e}"))?;
        let body = if self.title.is_empty() {
            root.clone()
        } else {
            let (top, rest) = root.split_vertically(TITLE_HEIGHT);
            let style = TextStyle::from((FONT_FAMILY, 22).into_font())
                .color(&BLACK)
                .pos(Pos::new(HPos::Center, VPos::Center));
            top.draw(&Text::new(
                self.title.clone(),
                (WIDTH as i32 / 2, TITLE_HEIGHT as i32 / 2),
                style,
            ))
            .map_err(|e| format!("title: {e}"))?;
            rest
        };
        let areas = body.split_evenly((self.panels.len(), 1));
        let n = self.panels.len();
        for (i, (panel, area)) in self.panels.iter().zip(areas.iter()).enumerate() {
            self.draw_panel(panel, area, i + 1 == n)
                .map_err(|e| format!("panel {} ({:?}): {e}", i, panel.caption))?;
        }
        Ok(())
    }
}

impl Figure {
    fn draw_panel<DB: DrawingBackend>(
        &self,
        panel: &PreparedPanel,
        area: &DrawingArea<DB, Shift>,
        bottom: bool,
    ) -> Result<(), String> {
        let (plot_area, legend_area) = area.split_horizontally(WIDTH - LEGEND_WIDTH);

        // Shared x axis: integer iteration ticks.
        let last = self.last_iter as f64;
        let (x_lo, x_hi) = if self.last_iter == 0 {
            (-1.0, 1.0)
        } else {
            (-0.02 * last, last * 1.02)
        };
        let x_ticks = iteration_ticks(self.last_iter);

        let (y_lo, y_hi, y_ticks, y_minor) = match &panel.axis {
            Some(a) => (a.lo, a.hi, a.ticks.clone(), a.minor.clone()),
            None => (0.0, 1.0, Vec::new(), Vec::new()),
        };

        let mut chart = ChartBuilder::on(&plot_area)
            .caption(&panel.caption, (FONT_FAMILY, 18))
            .margin(8)
            .margin_right(16)
            .x_label_area_size(42)
            .y_label_area_size(78)
            .build_cartesian_2d(
                TickedAxis::new(x_lo, x_hi, x_ticks, Vec::new()),
                TickedAxis::new(y_lo, y_hi, y_ticks, y_minor),
            )
            .map_err(|e| format!("axes: {e}"))?;

        let x_fmt = |v: &f64| format!("{:.0}", v.round());
        let y_fmt = |v: &f64| match &panel.axis {
            Some(a) => a.label(*v),
            None => String::new(),
        };
        let grid = RGBColor(225, 225, 225);
        let minor_grid = RGBColor(242, 242, 242);
        {
            let mut mesh = chart.configure_mesh();
            mesh.x_label_formatter(&x_fmt)
                .y_label_formatter(&y_fmt)
                .bold_line_style(grid)
                .light_line_style(minor_grid)
                .label_style((FONT_FAMILY, 14))
                .axis_desc_style((FONT_FAMILY, 15));
            if bottom {
                mesh.x_desc("iteration");
            }
            if !panel.y_label.is_empty() {
                mesh.y_desc(&panel.y_label);
            }
            mesh.draw().map_err(|e| format!("mesh: {e}"))?;
        }

        chart
            .plotting_area()
            .draw(&Rectangle::new(
                [(x_lo, y_lo), (x_hi, y_hi)],
                ShapeStyle::from(RGBColor(150, 150, 150)).stroke_width(1),
            ))
            .map_err(|e| format!("frame: {e}"))?;

        if panel.axis.is_none() {
            let style = TextStyle::from((FONT_FAMILY, 18).into_font())
                .color(&RGBColor(130, 130, 130))
                .pos(Pos::new(HPos::Center, VPos::Center));
            chart
                .plotting_area()
                .draw(&Text::new("no data", ((x_lo + x_hi) / 2.0, 0.5), style))
                .map_err(|e| format!("\"no data\" text: {e}"))?;
        }

        for (k, s) in panel.series.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let dashed = (k / PALETTE.len()) % 2 == 1;
            let line = ShapeStyle::from(color).stroke_width(2);
            for seg in &s.segments {
                if seg.len() >= 2 {
                    if dashed {
                        chart
                            .draw_series(DashedLineSeries::new(seg.iter().copied(), 8, 5, line))
                            .map_err(|e| format!("series {k}: {e}"))?;
                    } else {
                        chart
                            .draw_series(LineSeries::new(seg.iter().copied(), line))
                            .map_err(|e| format!("series {k}: {e}"))?;
                    }
                }
                if self.markers || seg.len() == 1 {
                    chart
                        .draw_series(
                            seg.iter()
                                .map(|&p| Circle::new(p, 3, ShapeStyle::from(color).filled())),
                        )
                        .map_err(|e| format!("series {k} markers: {e}"))?;
                }
            }
        }

        draw_legend(panel, &legend_area).map_err(|e| format!("legend: {e}"))
    }
}

/// A linear f64 axis with precomputed major/minor ticks (plotters'
/// `WithKeyPoints<RangedCoordf64>` can't take a custom label formatter).
struct TickedAxis {
    inner: RangedCoordf64,
    major: Vec<f64>,
    minor: Vec<f64>,
}

impl TickedAxis {
    fn new(lo: f64, hi: f64, major: Vec<f64>, minor: Vec<f64>) -> TickedAxis {
        TickedAxis {
            inner: (lo..hi).into(),
            major,
            minor,
        }
    }
}

impl Ranged for TickedAxis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.inner.map(value, limit)
    }

    fn key_points<Hint: KeyPointHint>(&self, hint: Hint) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.minor.clone()
        } else {
            self.major.clone()
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.inner.range()
    }
}

fn draw_legend<DB: DrawingBackend>(
    panel: &PreparedPanel,
    area: &DrawingArea<DB, Shift>,
) -> Result<(), String> {
    if panel.series.is_empty() {
        return Ok(());
    }
    let (_, h) = area.dim_in_pixel();
    let room = ((h as i32 - LEGEND_TOP - 8) / LEGEND_LINE).max(1) as usize;
    let total = panel.series.len();
    let shown = if total > room { room - 1 } else { total };
    let text = TextStyle::from((FONT_FAMILY, 14).into_font())
        .color(&BLACK)
        .pos(Pos::new(HPos::Left, VPos::Center));
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    for (k, s) in panel.series.iter().take(shown).enumerate() {
        let y = LEGEND_TOP + LEGEND_LINE * k as i32 + LEGEND_LINE / 2;
        let color = PALETTE[k % PALETTE.len()];
        let style = ShapeStyle::from(color).stroke_width(2);
        if (k / PALETTE.len()) % 2 == 1 {
            area.draw(&PathElement::new(vec![(4, y), (10, y)], style))
                .map_err(err)?;
            area.draw(&PathElement::new(vec![(16, y), (24, y)], style))
                .map_err(err)?;
        } else {
            area.draw(&PathElement::new(vec![(4, y), (24, y)], style))
                .map_err(err)?;
        }
        area.draw(&Text::new(s.label.clone(), (30, y), text.clone()))
            .map_err(err)?;
    }
    if shown < total {
        let y = LEGEND_TOP + LEGEND_LINE * shown as i32 + LEGEND_LINE / 2;
        area.draw(&Text::new(
            format!("+{} more", total - shown),
            (30, y),
            text.clone(),
        ))
        .map_err(err)?;
    }
    Ok(())
}

impl PreparedPanel {
    fn prepare(panel: &Panel) -> PreparedPanel {
        let finite = || {
            panel
                .series
                .iter()
                .flat_map(|s| s.values.iter().copied())
                .filter(|v| v.is_finite())
        };
        let any_finite = finite().next().is_some();
        let any_positive = finite().any(|v| v > 0.0);
        let mut caption = panel.title.clone();
        let scale = if panel.log_y && any_positive {
            YScale::Log10
        } else {
            if panel.log_y && any_finite {
                caption.push_str(" (linear: no positive values)");
            }
            YScale::Linear
        };
        let to_axis = |v: f64| -> Option<f64> {
            match scale {
                YScale::Linear if v.is_finite() => Some(v),
                YScale::Log10 if v.is_finite() && v > 0.0 => Some(v.log10()),
                _ => None,
            }
        };

        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let series: Vec<PreparedSeries> = panel
            .series
            .iter()
            .enumerate()
            .map(|(k, s)| {
                let mut segments = Vec::new();
                let mut cur: Vec<(f64, f64)> = Vec::new();
                for (i, &v) in s.values.iter().enumerate() {
                    match to_axis(v) {
                        Some(y) => {
                            lo = lo.min(y);
                            hi = hi.max(y);
                            cur.push((i as f64, y));
                        }
                        None if !cur.is_empty() => segments.push(std::mem::take(&mut cur)),
                        None => {}
                    }
                }
                if !cur.is_empty() {
                    segments.push(cur);
                }
                let mut label = if s.label.trim().is_empty() {
                    format!("series {k}")
                } else {
                    s.label.clone()
                };
                if segments.is_empty() {
                    label.push_str(" (no data)");
                }
                PreparedSeries {
                    label: truncate(&label, LEGEND_MAX_CHARS),
                    segments,
                }
            })
            .collect();

        let axis = (lo <= hi).then(|| YAxis::new(scale, lo, hi));
        PreparedPanel {
            caption,
            y_label: panel.y_label.clone(),
            axis,
            series,
        }
    }
}

fn truncate(s: &str, max_chars: usize) -> String {
    if s.chars().count() <= max_chars {
        s.to_string()
    } else {
        let mut t: String = s.chars().take(max_chars - 1).collect();
        t.push('…');
        t
    }
}

impl YAxis {
    /// `lo..=hi`: data range in axis space (finite, lo <= hi).
    fn new(scale: YScale, lo: f64, hi: f64) -> YAxis {
        match scale {
            YScale::Linear => {
                let (lo, hi) = pad_linear(lo, hi);
                let (ticks, step) = linear_ticks(lo, hi, 6);
                YAxis {
                    scale,
                    lo,
                    hi,
                    ticks,
                    minor: Vec::new(),
                    step,
                    magnitude: lo.abs().max(hi.abs()),
                }
            }
            YScale::Log10 => {
                let span = hi - lo;
                let (lo, hi) = if span < 1e-9 {
                    (lo - 0.3, hi + 0.3)
                } else {
                    (lo - 0.05 * span, hi + 0.05 * span)
                };
                let (ticks, minor, step) = log_ticks(lo, hi);
                YAxis {
                    scale,
                    lo,
                    hi,
                    ticks,
                    minor,
                    step,
                    magnitude: 0.0,
                }
            }
        }
    }

    /// Tick label for axis-space position `t`.
    fn label(&self, t: f64) -> String {
        match self.scale {
            YScale::Linear => fmt_tick(t, self.step, self.magnitude),
            YScale::Log10 => {
                let v = 10f64.powf(t);
                if self.step > 0.0 {
                    fmt_tick(v, self.step, 10f64.powf(self.hi))
                } else {
                    // decade / 1-2-5 ticks: resolution = the value's own decade
                    let decade = 10f64.powf((v.log10() + 1e-6).floor());
                    fmt_tick(v, decade, v)
                }
            }
        }
    }
}

/// Pads a linear data range; widens a (near-)constant one.
fn pad_linear(lo: f64, hi: f64) -> (f64, f64) {
    // keep hi - lo finite; values beyond +-MAX/4 end up off the chart
    let limit = f64::MAX / 4.0;
    let (lo, hi) = (lo.clamp(-limit, limit), hi.clamp(-limit, limit));
    let magnitude = lo.abs().max(hi.abs());
    let span = hi - lo;
    let (a, b) = if span <= magnitude * 1e-12 || span < 1e-300 {
        let pad = if magnitude > 1e-300 {
            magnitude * 0.1
        } else {
            1.0
        };
        (lo - pad, hi + pad)
    } else {
        (lo - 0.05 * span, hi + 0.05 * span)
    };
    (a, b)
}

/// A 1-2-5 step giving about `target` intervals over `span`.
fn nice_step(span: f64, target: usize) -> f64 {
    let raw = span / target.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let norm = raw / mag;
    let m = if norm <= 1.0 {
        1.0
    } else if norm <= 2.0 {
        2.0
    } else if norm <= 5.0 {
        5.0
    } else {
        10.0
    };
    m * mag
}

/// Multiples of a nice step within `[lo, hi]`, and the step.
fn linear_ticks(lo: f64, hi: f64, target: usize) -> (Vec<f64>, f64) {
    let span = hi - lo;
    if !(span.is_finite() && span > 0.0) {
        return (Vec::new(), 0.0);
    }
    let step = nice_step(span, target);
    if !(step.is_finite() && step > 0.0) {
        return (Vec::new(), 0.0);
    }
    let k0 = (lo / step).ceil();
    let k1 = (hi / step).floor();
    if !(k0.is_finite() && k1.is_finite()) || k1 < k0 || k1 - k0 > 100.0 {
        return (Vec::new(), step);
    }
    let ticks = (0..=(k1 - k0) as usize)
        .map(|i| {
            let t = (k0 + i as f64) * step;
            if t.abs() < step * 1e-9 { 0.0 } else { t }
        })
        .filter(|t| *t >= lo && *t <= hi)
        .collect();
    (ticks, step)
}

/// Ticks for a log10 axis over `[lo, hi]` (log10 units): major ticks, minor
/// ticks, and the linear label step (0 when labels are decades / 1-2-5).
fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>, f64) {
    let span = hi - lo;
    if !(span.is_finite() && span > 0.0) {
        return (Vec::new(), Vec::new(), 0.0);
    }
    let decades = |from: f64, to: f64| {
        let (a, b) = (from.ceil() as i64, to.floor() as i64);
        (a..=b.max(a - 1)).map(|e| e as f64)
    };
    // 10^t must be representable (labels are formatted from it)
    let (lo_ok, hi_ok) = (lo.max(-323.0), hi.min(308.0));
    if span >= 3.0 {
        // whole decades, every 1, 2, 5, 10, 20, ... decades (at most ~8 labels)
        let every = nice_step(span, 8).round().max(1.0) as i64;
        let major: Vec<f64> = decades(lo_ok, hi_ok)
            .filter(|e| (*e as i64).rem_euclid(every) == 0)
            .collect();
        let minor: Vec<f64> = if every > 1 {
            if span <= 60.0 {
                decades(lo_ok, hi_ok)
                    .filter(|e| !major.contains(e))
                    .collect()
            } else {
                Vec::new()
            }
        } else if span <= 6.0 {
            decades(lo - 1.0, hi)
                .flat_map(|e| (2..=9).map(move |m| e + (m as f64).log10()))
                .filter(|t| *t >= lo && *t <= hi)
                .collect()
        } else {
            Vec::new()
        };
        (major, minor, 0.0)
    } else if span >= 0.9 {
        // 1-2-5 per decade, minor ticks on the other integers
        let mut major = Vec::new();
        let mut minor = Vec::new();
        for e in decades(lo_ok - 1.0, hi_ok + 1.0) {
            for m in 1..=9 {
                let t = e + (m as f64).log10();
                if t < lo || t > hi {
                    continue;
                }
                if matches!(m, 1 | 2 | 5) {
                    major.push(t);
                } else {
                    minor.push(t);
                }
            }
        }
        (major, minor, 0.0)
    } else {
        // less than a decade: linear nice values, placed logarithmically
        let (vlo, vhi) = (10f64.powf(lo), 10f64.powf(hi));
        let (vals, step) = linear_ticks(vlo, vhi, 5);
        let major = vals
            .into_iter()
            .filter(|v| *v > 0.0)
            .map(f64::log10)
            .filter(|t| t.is_finite())
            .collect();
        (major, Vec::new(), step)
    }
}

/// Iteration ticks: integer multiples of a 1-2-5 step in `0..=last`.
fn iteration_ticks(last: usize) -> Vec<f64> {
    if last == 0 {
        return vec![0.0];
    }
    let step = nice_step(last as f64, 8).round().max(1.0) as usize;
    (0..=last).step_by(step).map(|i| i as f64).collect()
}

/// Formats a tick value `v` on an axis with tick spacing `step`; `magnitude`
/// (largest |value| on the axis) chooses plain vs. scientific notation.
fn fmt_tick(v: f64, step: f64, magnitude: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    if v == 0.0 || (step > 0.0 && v.abs() < step * 1e-6) {
        return "0".into();
    }
    let step_exp = if step > 0.0 {
        (step.log10() + 1e-6).floor()
    } else {
        (v.abs().log10() + 1e-6).floor()
    };
    if (1e-3..1e6).contains(&magnitude) && step_exp >= -6.0 {
        let decimals = (-step_exp).clamp(0.0, 12.0) as usize;
        format!("{v:.decimals$}")
    } else {
        let v_exp = (v.abs().log10() + 1e-6).floor();
        let decimals = (v_exp - step_exp).clamp(0.0, 6.0) as usize;
        format!("{v:.decimals$e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch_dir(name: &str) -> PathBuf {
        static N: AtomicU64 = AtomicU64::new(0);
        let dir = std::env::temp_dir().join(format!(
            "softc-plot-test-{}-{}-{name}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn series(label: &str, values: Vec<f64>) -> Series {
        Series {
            label: label.into(),
            values,
        }
    }

    fn panel(title: &str, y_label: &str, log_y: bool, series: Vec<Series>) -> Panel {
        Panel {
            title: title.into(),
            y_label: y_label.into(),
            log_y,
            series,
        }
    }

    /// Contents of the SVG's `<text>` elements, trimmed.
    fn svg_texts(svg: &str) -> Vec<String> {
        svg.split("<text")
            .skip(1)
            .filter_map(|t| {
                let body = &t[t.find('>')? + 1..];
                Some(body[..body.find("</text>")?].trim().to_string())
            })
            .collect()
    }

    fn png_dims(bytes: &[u8]) -> (u32, u32) {
        let w = u32::from_be_bytes(bytes[16..20].try_into().unwrap());
        let h = u32::from_be_bytes(bytes[20..24].try_into().unwrap());
        (w, h)
    }

    /// Writes the figure, checks both files, no leftover temp files; returns
    /// (png bytes, svg text).
    fn write_ok(name: &str, title: &str, panels: &[Panel]) -> (Vec<u8>, Vec<String>) {
        let dir = scratch_dir(name);
        let stem = dir.join(name);
        let paths = write_figure(&stem, title, panels).expect("write_figure failed");
        assert_eq!(
            paths,
            vec![
                dir.join(format!("{name}.png")),
                dir.join(format!("{name}.svg"))
            ]
        );
        let png = std::fs::read(&paths[0]).unwrap();
        let svg = std::fs::read_to_string(&paths[1]).unwrap();
        assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"), "not a PNG");
        assert!(
            png.len() > 2_000,
            "PNG suspiciously small: {} bytes",
            png.len()
        );
        let title_h = if title.is_empty() { 0 } else { TITLE_HEIGHT };
        assert_eq!(
            png_dims(&png),
            (WIDTH, title_h + PANEL_HEIGHT * panels.len() as u32)
        );
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        let mut names: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(
            names,
            vec![format!("{name}.png"), format!("{name}.svg")],
            "leftovers"
        );
        if std::env::var_os("SOFTC_PLOT_KEEP").is_none() {
            let _ = std::fs::remove_dir_all(&dir);
        } else {
            eprintln!("kept {}", dir.display());
        }
        (png, svg_texts(&svg))
    }

    fn history(n: usize) -> Vec<Panel> {
        let loss: Vec<f64> = (0..n)
            .map(|i| 10.0 * (-(i as f64) / 8.0).exp() + 1e-3)
            .collect();
        let val: Vec<f64> = (0..n)
            .map(|i| {
                if i % 7 == 3 {
                    f64::NAN
                } else {
                    12.0 * (-(i as f64) / 10.0).exp() + 0.01
                }
            })
            .collect();
        let stiffness: Vec<f64> = (0..n).map(|i| 1.0 + 0.5 * (i as f64 / 5.0).sin()).collect();
        let damping: Vec<f64> = (0..n).map(|i| 0.2 - 0.01 * i as f64).collect();
        let grad: Vec<f64> = (0..n).map(|i| 10f64.powf(-(i as f64) / 4.0)).collect();
        vec![
            panel(
                "loss",
                "loss",
                true,
                vec![series("train loss", loss), series("validation loss", val)],
            ),
            panel(
                "parameters",
                "value",
                false,
                vec![
                    series("stiffness k", stiffness),
                    series("damping c", damping),
                ],
            ),
            panel(
                "gradient norm",
                "|grad|",
                true,
                vec![series("grad norm", grad)],
            ),
        ]
    }

    #[test]
    fn three_panels_png_and_svg() {
        let (_, svg) = write_ok("history", "softc optimisation", &history(40));
        for text in [
            "softc optimisation",
            "loss",
            "parameters",
            "gradient norm",
            "train loss",
            "validation loss",
            "stiffness k",
            "damping c",
            "grad norm",
            "iteration",
        ] {
            assert!(
                svg.iter().any(|t| t == text),
                "SVG lacks text {text:?}: {svg:?}"
            );
        }
    }

    #[test]
    fn single_iteration() {
        let panels = vec![
            panel("loss", "loss", true, vec![series("loss", vec![0.5])]),
            panel("param", "", false, vec![series("p", vec![-3.0])]),
        ];
        write_ok("one", "one iteration", &panels);
    }

    #[test]
    fn all_nan_and_empty() {
        let panels = vec![
            panel("nan", "y", false, vec![series("a", vec![f64::NAN; 5])]),
            panel(
                "nan log",
                "y",
                true,
                vec![series("b", vec![f64::NAN, f64::INFINITY])],
            ),
            panel("no series", "y", false, vec![]),
            panel("empty series", "y", true, vec![series("c", vec![])]),
        ];
        let (_, svg) = write_ok("nan", "", &panels);
        assert!(svg.iter().any(|t| t == "no data"));
        assert!(svg.iter().any(|t| t == "a (no data)"));
    }

    #[test]
    fn log_panel_with_zeros_and_negatives() {
        let panels = vec![
            panel(
                "zeros",
                "loss",
                true,
                vec![series("l", vec![1.0, 0.0, 0.1, 0.0, 1e-4, -1.0])],
            ),
            panel(
                "all zero",
                "loss",
                true,
                vec![series("z", vec![0.0, 0.0, 0.0])],
            ),
            panel(
                "negative",
                "loss",
                true,
                vec![series("n", vec![-1.0, -2.0])],
            ),
        ];
        let (_, svg) = write_ok("logzero", "log", &panels);
        assert!(
            svg.iter()
                .any(|t| t == "all zero (linear: no positive values)")
        );
    }

    #[test]
    fn constant_many_series_and_extremes() {
        let many: Vec<Series> = (0..20)
            .map(|k| {
                series(
                    &format!("param_{k}"),
                    (0..300).map(|i| (k * i) as f64).collect(),
                )
            })
            .collect();
        let panels = vec![
            panel("constant", "c", false, vec![series("c", vec![2.5; 30])]),
            panel("constant log", "c", true, vec![series("c", vec![3e-7; 30])]),
            panel("zero", "c", false, vec![series("z", vec![0.0; 30])]),
            panel("many", "v", false, many),
            panel(
                "huge",
                "v",
                false,
                vec![series("h", vec![-f64::MAX, f64::MAX, 1.0])],
            ),
            panel(
                "tiny",
                "v",
                true,
                vec![series("t", vec![1e-300, 1e-320, 5e-324, 1e300])],
            ),
            panel(
                "a very long title that goes on and on and on <&> ünïcode ✓",
                "y",
                false,
                vec![series(
                    "a label that is much too long for the legend column",
                    vec![1.0, 2.0],
                )],
            ),
        ];
        let (_, svg) = write_ok("stress", "stress", &panels);
        assert!(svg.iter().any(|t| t == "param_0"));
        assert!(svg.iter().any(|t| t == "param_10"));
        // decade labels every 100 decades, none from an underflowed 10^t
        for l in ["1e-300", "1e-200", "1", "1e300"] {
            assert!(svg.iter().any(|t| t == l), "missing tick {l}");
        }
        assert!(!svg.iter().any(|t| t.contains("inf") || t.contains("NaN")));
        assert!(svg.iter().any(|t| t == "+7 more"), "{svg:?}");
        assert!(!svg.iter().any(|t| t == "param_13"));
        assert!(svg.iter().any(|t| t.contains("&lt;&amp;&gt;")));
    }

    #[test]
    fn errors_are_reported() {
        let dir = scratch_dir("err");
        assert!(write_figure(&dir.join("x"), "t", &[]).is_err());
        // parent "folder" is a regular file
        let file = dir.join("file");
        std::fs::write(&file, b"x").unwrap();
        let err = write_figure(&file.join("x"), "t", &history(3)).unwrap_err();
        assert!(err.contains("plot:"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn tick_labels() {
        assert_eq!(fmt_tick(0.30000000000000004, 0.1, 1.0), "0.3");
        assert_eq!(fmt_tick(1500.0, 500.0, 2000.0), "1500");
        assert_eq!(fmt_tick(1.5e7, 5e6, 2e7), "1.5e7");
        assert_eq!(fmt_tick(1e-7, 1e-7, 1e-7), "1e-7");
        assert_eq!(fmt_tick(-1e-17, 0.2, 1.0), "0");
        assert_eq!(iteration_ticks(0), vec![0.0]);
        assert_eq!(iteration_ticks(3), vec![0.0, 1.0, 2.0, 3.0]);
        assert_eq!(
            iteration_ticks(100),
            vec![0.0, 20.0, 40.0, 60.0, 80.0, 100.0]
        );
        let (major, _, step) = log_ticks(-8.2, 0.3);
        assert_eq!(step, 0.0);
        assert!(major.iter().all(|t| t.fract() == 0.0) && major.len() >= 4);
    }
}

// ---------------------------------------------------------------------------
// Scatter figures (speed against accuracy)

/// One point of a log-log scatter.
#[derive(Clone, Debug, PartialEq)]
pub struct ScatterPoint {
    pub x: f64,
    pub y: f64,
    /// Points of one group share a colour and a legend entry.
    pub group: String,
    /// Written beside the point.
    pub label: String,
    /// Ringed and joined by a line (e.g. the Pareto front).
    pub highlight: bool,
}

struct Scatter {
    title: String,
    x_label: String,
    y_label: String,
    points: Vec<ScatterPoint>,
}

/// Writes `<stem>.png` and `<stem>.svg`: a log-log scatter of `points`, coloured by group, with
/// the highlighted points ringed and joined in order of x. A y of exactly 0 (an error measured
/// against the point itself) is drawn at the axis' floor, a decade below the smallest positive
/// y, and labelled `(0)`; other non-positive or non-finite values are left out.
pub fn write_scatter(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    points: &[ScatterPoint],
) -> Result<Vec<PathBuf>, String> {
    let drawable = |p: &&ScatterPoint| p.x.is_finite() && p.x > 0.0 && p.y.is_finite();
    let floor = points
        .iter()
        .filter(drawable)
        .map(|p| p.y)
        .filter(|&y| y > 0.0)
        .fold(f64::INFINITY, f64::min);
    let floor = if floor.is_finite() {
        floor / 10.0
    } else {
        1e-16
    };
    let points: Vec<ScatterPoint> = points
        .iter()
        .filter(drawable)
        .filter(|p| p.y >= 0.0)
        .map(|p| match p.y {
            0.0 => ScatterPoint {
                y: floor,
                label: format!("{} (0)", p.label),
                ..p.clone()
            },
            _ => p.clone(),
        })
        .collect();
    if points.is_empty() {
        return Err("plot: no point with positive, finite coordinates to draw".into());
    }
    write_chart(
        stem,
        &Scatter {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            points,
        },
    )
}

impl Chart for Scatter {
    fn size(&self) -> (u32, u32) {
        (WIDTH, 600)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        root.fill(&WHITE).map_err(|e| format!("background: {e}"))?;
        let range = |f: fn(&ScatterPoint) -> f64| {
            let lo = self.points.iter().map(f).fold(f64::INFINITY, f64::min);
            let hi = self.points.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
            // Half a decade of margin, so labels and rings stay inside.
            (lo / 10f64.powf(0.25), hi * 10f64.powf(0.25))
        };
        let (x0, x1) = range(|p| p.x);
        let (y0, y1) = range(|p| p.y);
        let (plot, legend) = root.split_horizontally(WIDTH - LEGEND_WIDTH);
        let mut chart = ChartBuilder::on(&plot)
            .caption(&self.title, (FONT_FAMILY, 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(|e| format!("axes: {e}"))?;
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .x_label_formatter(&|v| format!("{v:.2e}"))
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .label_style((FONT_FAMILY, 12))
            .draw()
            .map_err(|e| format!("grid: {e}"))?;
        let mut groups: Vec<&str> = Vec::new();
        for p in &self.points {
            if !groups.contains(&p.group.as_str()) {
                groups.push(&p.group);
            }
        }
        let colour = |g: &str| PALETTE[groups.iter().position(|x| *x == g).unwrap_or(0) % 10];
        let mut front: Vec<&ScatterPoint> = self.points.iter().filter(|p| p.highlight).collect();
        front.sort_by(|a, b| a.x.total_cmp(&b.x));
        chart
            .draw_series(LineSeries::new(
                front.iter().map(|p| (p.x, p.y)),
                BLACK.stroke_width(1),
            ))
            .map_err(|e| format!("front: {e}"))?;
        for p in &self.points {
            let c = colour(&p.group);
            chart
                .draw_series(std::iter::once(Circle::new((p.x, p.y), 4, c.filled())))
                .map_err(|e| format!("point: {e}"))?;
            if p.highlight {
                chart
                    .draw_series(std::iter::once(Circle::new(
                        (p.x, p.y),
                        8,
                        BLACK.stroke_width(2),
                    )))
                    .map_err(|e| format!("ring: {e}"))?;
            }
            chart
                .draw_series(std::iter::once(Text::new(
                    p.label.clone(),
                    (p.x, p.y),
                    (FONT_FAMILY, 10).into_font().color(&c),
                )))
                .map_err(|e| format!("label: {e}"))?;
        }
        // Legend: one line per group, then the front.
        let style = TextStyle::from((FONT_FAMILY, 13).into_font()).color(&BLACK);
        let mut y = LEGEND_TOP;
        for g in &groups {
            legend
                .draw(&Circle::new((12, y), 5, colour(g).filled()))
                .map_err(|e| format!("legend: {e}"))?;
            legend
                .draw(&Text::new(
                    truncate(g, LEGEND_MAX_CHARS),
                    (24, y - 7),
                    style.clone(),
                ))
                .map_err(|e| format!("legend: {e}"))?;
            y += LEGEND_LINE;
        }
        legend
            .draw(&Circle::new((12, y), 7, BLACK.stroke_width(2)))
            .map_err(|e| format!("legend: {e}"))?;
        legend
            .draw(&Text::new("Pareto front", (24, y - 7), style))
            .map_err(|e| format!("legend: {e}"))?;
        Ok(())
    }
}

#[cfg(test)]
mod scatter_tests {
    use super::*;

    #[test]
    fn a_scatter_is_written_as_png_and_svg() {
        let dir = std::env::temp_dir().join(format!("softc-scatter-{}", std::process::id()));
        let points: Vec<ScatterPoint> = (1..6)
            .map(|i| ScatterPoint {
                x: i as f64,
                y: 1.0 / (i * i) as f64,
                group: if i % 2 == 0 { "even" } else { "odd" }.into(),
                label: format!("p{i}"),
                highlight: i > 2,
            })
            .collect();
        let files = write_scatter(&dir.join("s"), "t", "x", "y", &points).unwrap();
        let svg = std::fs::read_to_string(&files[1]).unwrap();
        assert!(svg.contains("Pareto front") && svg.contains("p3"));
        assert!(std::fs::metadata(&files[0]).unwrap().len() > 1000);
        let none = write_scatter(&dir.join("n"), "t", "x", "y", &[]);
        assert!(none.is_err());
        // One point whose error is 0 (the study's own reference): drawn at the floor.
        let alone = ScatterPoint {
            y: 0.0,
            ..points[0].clone()
        };
        let files = write_scatter(&dir.join("one"), "t", "x", "y", &[alone]).unwrap();
        let svg = std::fs::read_to_string(&files[1]).unwrap();
        assert!(svg.contains("p1 (0)"), "{svg}");
        let _ = std::fs::remove_dir_all(dir);
    }
}
