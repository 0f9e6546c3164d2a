//! Small line plots rendered straight to an `image::RgbImage` (save it as PNG) for benchmark
//! and convergence reports: no plotting crate and no font files, just an embedded 5x7 font.

use image::{Rgb, RgbImage};

/// Distinct colours for series, in the order they are meant to be used.
pub const PALETTE: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [23, 190, 207],
];

/// One named polyline of `(x, y)` points.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub colour: [u8; 3],
}

/// How an axis maps data values to positions.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Scale {
    Linear,
    Log10,
}

/// A line plot: build it with [`Plot::new`] and the builder methods, then [`Plot::render`].
#[derive(Clone, Debug, PartialEq)]
pub struct Plot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x_scale: Scale,
    pub y_scale: Scale,
    pub series: Vec<Series>,
    pub width: u32,
    pub height: u32,
}

/// Every font pixel is drawn as a `FONT_SCALE` x `FONT_SCALE` square.
const FONT_SCALE: i64 = 2;
const GLYPH_W: i64 = 5;
const TEXT_H: i64 = 7 * FONT_SCALE;
const ADVANCE: i64 = (GLYPH_W + 1) * FONT_SCALE;
const MARGIN: i64 = 10;
const TOP_PAD: i64 = 12;
const TICK_LEN: i64 = 5;
const LABEL_GAP: i64 = 3;
/// Images are clamped to `1..=MAX_SIDE` pixels per side.
const MAX_SIDE: u32 = 8192;
/// Series with more drawable points than this get no markers (they would merge into a band).
const MAX_MARKED_POINTS: usize = 200;

const WHITE: [u8; 3] = [255, 255, 255];
const TEXT: [u8; 3] = [20, 20, 20];
const AXIS: [u8; 3] = [60, 60, 60];
const GRID: [u8; 3] = [225, 225, 225];
const LEGEND_BORDER: [u8; 3] = [170, 170, 170];

/// Seven rows of five bits each, top row first; bit 4 (0x10) is the leftmost column.
type Glyph = [u8; 7];

const UNKNOWN_GLYPH: Glyph = [0x00, 0x1F, 0x11, 0x11, 0x11, 0x1F, 0x00];

#[rustfmt::skip]
const FONT: &[(char, Glyph)] = &[
    (' ', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00]), ('0', [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E]),
    ('1', [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E]), ('2', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F]),
    ('3', [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E]), ('4', [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02]),
    ('5', [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E]), ('6', [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E]),
    ('7', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]), ('8', [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E]),
    ('9', [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C]), ('a', [0x00, 0x00, 0x0E, 0x01, 0x0F, 0x11, 0x0F]),
    ('b', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x1E]), ('c', [0x00, 0x00, 0x0E, 0x10, 0x10, 0x11, 0x0E]),
    ('d', [0x01, 0x01, 0x0D, 0x13, 0x11, 0x11, 0x0F]), ('e', [0x00, 0x00, 0x0E, 0x11, 0x1F, 0x10, 0x0E]),
    ('f', [0x06, 0x09, 0x08, 0x1C, 0x08, 0x08, 0x08]), ('g', [0x00, 0x00, 0x0F, 0x11, 0x0F, 0x01, 0x0E]),
    ('h', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11]), ('i', [0x04, 0x00, 0x0C, 0x04, 0x04, 0x04, 0x0E]),
    ('j', [0x02, 0x00, 0x06, 0x02, 0x02, 0x12, 0x0C]), ('k', [0x10, 0x10, 0x12, 0x14, 0x18, 0x14, 0x12]),
    ('l', [0x0C, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]), ('m', [0x00, 0x00, 0x1A, 0x15, 0x15, 0x11, 0x11]),
    ('n', [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11]), ('o', [0x00, 0x00, 0x0E, 0x11, 0x11, 0x11, 0x0E]),
    ('p', [0x00, 0x00, 0x1E, 0x11, 0x1E, 0x10, 0x10]), ('q', [0x00, 0x00, 0x0F, 0x11, 0x0F, 0x01, 0x01]),
    ('r', [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10]), ('s', [0x00, 0x00, 0x0F, 0x10, 0x0E, 0x01, 0x1E]),
    ('t', [0x08, 0x08, 0x1C, 0x08, 0x08, 0x09, 0x06]), ('u', [0x00, 0x00, 0x11, 0x11, 0x11, 0x13, 0x0D]),
    ('v', [0x00, 0x00, 0x11, 0x11, 0x11, 0x0A, 0x04]), ('w', [0x00, 0x00, 0x11, 0x11, 0x15, 0x15, 0x0A]),
    ('x', [0x00, 0x00, 0x11, 0x0A, 0x04, 0x0A, 0x11]), ('y', [0x00, 0x00, 0x11, 0x11, 0x0F, 0x01, 0x0E]),
    ('z', [0x00, 0x00, 0x1F, 0x02, 0x04, 0x08, 0x1F]), ('A', [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]),
    ('B', [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E]), ('C', [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E]),
    ('D', [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C]), ('E', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F]),
    ('F', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10]), ('G', [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F]),
    ('H', [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]), ('I', [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('J', [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C]), ('K', [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11]),
    ('L', [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F]), ('M', [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11]),
    ('N', [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11]), ('O', [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('P', [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10]), ('Q', [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D]),
    ('R', [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11]), ('S', [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E]),
    ('T', [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]), ('U', [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('V', [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04]), ('W', [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A]),
    ('X', [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11]), ('Y', [0x11, 0x11, 0x0A, 0x04, 0x04, 0x04, 0x04]),
    ('Z', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F]), ('.', [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C]),
    (',', [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08]), ('-', [0x00, 0x00, 0x00, 0x0E, 0x00, 0x00, 0x00]),
    ('+', [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00]), ('_', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F]),
    ('/', [0x01, 0x01, 0x02, 0x04, 0x08, 0x10, 0x10]), ('(', [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02]),
    (')', [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08]), ('[', [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E]),
    (']', [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E]), (':', [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00]),
    ('%', [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03]), ('=', [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00]),
    ('^', [0x04, 0x0A, 0x11, 0x00, 0x00, 0x00, 0x00]), ('*', [0x00, 0x04, 0x15, 0x0E, 0x15, 0x04, 0x00]),
    ('<', [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02]), ('>', [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08]),
    ('|', [0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]), ('!', [0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04]),
    ('?', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04]), ('\'', [0x04, 0x04, 0x08, 0x00, 0x00, 0x00, 0x00]),
];

impl Plot {
    /// An 800x500 plot with linear axes and no series.
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Self {
            title: title.to_string(),
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            x_scale: Scale::Linear,
            y_scale: Scale::Linear,
            series: Vec::new(),
            width: 800,
            height: 500,
        }
    }

    /// Use a base-10 logarithmic x axis.
    pub fn log_x(mut self) -> Self {
        self.x_scale = Scale::Log10;
        self
    }

    /// Use a base-10 logarithmic y axis.
    pub fn log_y(mut self) -> Self {
        self.y_scale = Scale::Log10;
        self
    }

    /// Add a series; points that cannot be drawn (non-finite, or <= 0 on a log axis) are skipped.
    pub fn series(mut self, name: &str, colour: [u8; 3], points: Vec<(f64, f64)>) -> Self {
        let name = name.to_string();
        self.series.push(Series {
            name,
            points,
            colour,
        });
        self
    }

    /// Draw the plot. Never panics; each side is clamped to `1..=8192` pixels.
    pub fn render(&self) -> RgbImage {
        let width = self.width.clamp(1, MAX_SIDE);
        let height = self.height.clamp(1, MAX_SIDE);
        let mut img = RgbImage::from_pixel(width, height, Rgb(WHITE));
        let frame = Frame::fit(self, i64::from(width), i64::from(height));
        frame.draw_ticks(&mut img);
        for series in &self.series {
            self.draw_series(&mut img, &frame, series);
        }
        draw_box(
            &mut img,
            frame.left,
            frame.top,
            frame.right,
            frame.bottom,
            AXIS,
        );
        frame.draw_legend(&mut img, &self.series);
        self.draw_labels(&mut img, &frame);
        img
    }

    fn is_drawable(&self, (x, y): (f64, f64)) -> bool {
        valid_for(self.x_scale, x) && valid_for(self.y_scale, y)
    }

    /// Polyline (broken at undrawable points) plus small square markers.
    fn draw_series(&self, img: &mut RgbImage, frame: &Frame, series: &Series) {
        let mut previous: Option<(i64, i64)> = None;
        for &p in &series.points {
            if !self.is_drawable(p) {
                previous = None;
                continue;
            }
            let q = frame.to_px(p);
            if let Some(prev) = previous {
                draw_line(img, prev, q, series.colour);
            }
            previous = Some(q);
        }
        let drawable: Vec<(f64, f64)> = series
            .points
            .iter()
            .copied()
            .filter(|&p| self.is_drawable(p))
            .collect();
        if drawable.len() <= MAX_MARKED_POINTS {
            for &p in &drawable {
                let (x, y) = frame.to_px(p);
                fill_rect(img, x - 2, y - 2, x + 3, y + 3, series.colour);
            }
        }
    }

    /// Title centred on top, y label above the y axis, x label centred below the plot area.
    fn draw_labels(&self, img: &mut RgbImage, frame: &Frame) {
        let title_x = (i64::from(img.width()) - text_width(&self.title)) / 2;
        draw_text(img, title_x, TOP_PAD, &self.title);
        draw_text(img, MARGIN, TOP_PAD + TEXT_H + 10, &self.y_label);
        let x_label_x = (frame.left + frame.right - text_width(&self.x_label)) / 2;
        let x_label_y = frame.bottom + TICK_LEN + LABEL_GAP + TEXT_H + 8;
        draw_text(img, x_label_x, x_label_y, &self.x_label);
    }
}

fn valid_for(scale: Scale, v: f64) -> bool {
    v.is_finite() && (scale == Scale::Linear || v > 0.0)
}

/// A fitted axis: `lo..hi` is the shown range (in log10 units for `Scale::Log10`).
#[derive(Debug)]
struct Axis {
    scale: Scale,
    lo: f64,
    hi: f64,
    ticks: Vec<(f64, String)>,
}

impl Axis {
    /// Fit an axis to drawable values; defaults to 0..1 (linear) or 1..10 (log) when empty.
    fn fit(scale: Scale, values: &[f64]) -> Self {
        let (min, max) = values
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let has_data = min <= max;
        match scale {
            Scale::Linear => {
                let (min, max) = if has_data {
                    widen_degenerate(min, max)
                } else {
                    (0.0, 1.0)
                };
                let values = linear_ticks(min, max);
                let lo = values.first().map_or(min, |&t| t.min(min));
                let hi = values.last().map_or(max, |&t| t.max(max));
                let ticks = values.iter().copied().zip(linear_labels(&values)).collect();
                Self {
                    scale,
                    lo,
                    hi,
                    ticks,
                }
            }
            Scale::Log10 => {
                let (min, max) = if has_data { (min, max) } else { (1.0, 10.0) };
                let (lo_exp, hi_exp) = decade_bounds(min, max);
                let ticks = log_ticks(lo_exp, hi_exp);
                Self {
                    scale,
                    lo: f64::from(lo_exp),
                    hi: f64::from(hi_exp),
                    ticks,
                }
            }
        }
    }

    /// Position of `v` along the axis, 0 at `lo` and 1 at `hi`, clamped to -1..2 so that
    /// pixel coordinates (and line lengths) stay small.
    fn fraction(&self, v: f64) -> f64 {
        let pos = match self.scale {
            Scale::Linear => v,
            Scale::Log10 => v.log10(),
        };
        let t = (pos - self.lo) / (self.hi - self.lo);
        if t.is_nan() {
            0.0
        } else {
            t.clamp(-1.0, 2.0)
        }
    }

    fn widest_label(&self) -> i64 {
        self.ticks
            .iter()
            .map(|(_, label)| text_width(label))
            .max()
            .unwrap_or(0)
    }
}

fn pow10(exp: i32) -> f64 {
    10f64.powi(exp)
}

/// Integer power of ten at or below `|v|` (0 for zero or non-finite values).
fn exponent_of(v: f64) -> i32 {
    if v == 0.0 || !v.is_finite() {
        0
    } else {
        (v.abs().log10() + 1e-9).floor() as i32
    }
}

/// Widen an (almost) empty range around its centre.
fn widen_degenerate(min: f64, max: f64) -> (f64, f64) {
    let magnitude = min.abs().max(max.abs());
    if max - min > magnitude * 1e-12 && max - min > 1e-300 {
        return (min, max);
    }
    let centre = 0.5 * min + 0.5 * max;
    let half = if centre.abs() > 1e-300 {
        centre.abs() * 0.1
    } else {
        1.0
    };
    (centre - half, centre + half)
}

/// At most 7 ticks at a "nice" step (1, 2 or 5 times a power of ten) covering `min..max`.
fn linear_ticks(min: f64, max: f64) -> Vec<f64> {
    let span = max - min;
    if !(span.is_finite() && span > 0.0) {
        return vec![min, max];
    }
    let first_exp = span.log10().floor() as i32 - 1;
    for exp in first_exp..=first_exp + 2 {
        for mantissa in [1.0, 2.0, 5.0] {
            let step = mantissa * pow10(exp);
            let first = (min / step + 1e-9).floor();
            let intervals = (max / step - 1e-9).ceil() - first;
            if intervals.is_finite() && (0.0..=6.0).contains(&intervals) {
                return (0..=intervals as i64)
                    .map(|i| (first + i as f64) * step)
                    .collect();
            }
        }
    }
    vec![min, max]
}

/// Labels for evenly spaced ticks: fixed point with the decimals the step needs, or
/// scientific (`1.5e-4`) when the values are very large or the step very small.
fn linear_labels(ticks: &[f64]) -> Vec<String> {
    let step = match ticks {
        [a, b, ..] => (b - a).abs(),
        _ => 1.0,
    };
    let largest = ticks.iter().fold(0.0_f64, |m, t| m.max(t.abs()));
    let scientific = largest >= 1e5 || step < 1e-3;
    let label = |v: f64| {
        if v == 0.0 || (step.is_finite() && v.abs() < step * 1e-6) {
            "0".to_string()
        } else if scientific {
            let digits = (exponent_of(v) - exponent_of(step)).clamp(0, 6) as usize;
            trim_zeros(&format!("{:.*e}", digits, v))
        } else {
            let decimals = (-exponent_of(step)).clamp(0, 12) as usize;
            trim_zeros(&format!("{:.*}", decimals, v))
        }
    };
    ticks.iter().map(|&v| label(v)).collect()
}

/// Drop trailing zeros (and a bare '.') from a mantissa: "1.500e-4" -> "1.5e-4", "2.50" -> "2.5".
fn trim_zeros(s: &str) -> String {
    let (mantissa, exponent) = match s.split_once('e') {
        Some((m, e)) => (m, format!("e{e}")),
        None => (s, String::new()),
    };
    if mantissa.contains('.') {
        format!(
            "{}{exponent}",
            mantissa.trim_end_matches('0').trim_end_matches('.')
        )
    } else {
        s.to_string()
    }
}

/// Whole-decade bounds (as exponents) enclosing `min..max`: at least one decade, and a
/// multiple of the tick stride.
fn decade_bounds(min: f64, max: f64) -> (i32, i32) {
    let lo = (min.log10() + 1e-9).floor() as i32;
    let hi = ((max.log10() - 1e-9).ceil() as i32).max(lo + 1);
    let stride = decade_stride(hi - lo);
    (lo, lo + (hi - lo + stride - 1) / stride * stride)
}

/// Decades between labelled ticks, keeping at most 7 ticks.
fn decade_stride(decades: i32) -> i32 {
    ((decades + 5) / 6).max(1)
}

/// Ticks from `10^lo_exp` to `10^hi_exp`: every (strided) decade, plus the 2 and 5
/// multiples when the range spans fewer than 3 decades.
fn log_ticks(lo_exp: i32, hi_exp: i32) -> Vec<(f64, String)> {
    let decades = hi_exp - lo_exp;
    let mut marks: Vec<(i32, i32)> = Vec::new();
    if decades < 3 {
        for exp in lo_exp..hi_exp {
            marks.extend([(1, exp), (2, exp), (5, exp)]);
        }
        marks.push((1, hi_exp));
    } else {
        let stride = usize::try_from(decade_stride(decades)).unwrap_or(1);
        marks.extend((lo_exp..=hi_exp).step_by(stride).map(|exp| (1, exp)));
    }
    let value = |m: i32, e: i32| f64::from(m) * pow10(e);
    marks
        .into_iter()
        .map(|(m, e)| (value(m, e), log_label(m, e, decades < 3)))
        .collect()
}

/// "2e5" style, or a plain number ("20", "0.05") when `plain` and it is short.
fn log_label(mantissa: i32, exp: i32, plain: bool) -> String {
    if plain && (0..=3).contains(&exp) {
        (i64::from(mantissa) * 10i64.pow(exp as u32)).to_string()
    } else if plain && (-3..0).contains(&exp) {
        format!("0.{}{mantissa}", "0".repeat((-exp - 1) as usize))
    } else {
        format!("{mantissa}e{exp}")
    }
}

/// Both axes and the plot area in pixels (inclusive edges).
#[derive(Debug)]
struct Frame {
    x: Axis,
    y: Axis,
    left: i64,
    top: i64,
    right: i64,
    bottom: i64,
}

impl Frame {
    /// Fit the axes to the plot's drawable points and leave margins for the labels.
    fn fit(plot: &Plot, width: i64, height: i64) -> Self {
        let (xs, ys): (Vec<f64>, Vec<f64>) = plot
            .series
            .iter()
            .flat_map(|s| s.points.iter().copied())
            .filter(|&p| plot.is_drawable(p))
            .unzip();
        let x = Axis::fit(plot.x_scale, &xs);
        let y = Axis::fit(plot.y_scale, &ys);
        let left = MARGIN + y.widest_label() + TICK_LEN + LABEL_GAP + 2;
        let right_margin = (x.widest_label() / 2 + MARGIN).max(24);
        let top = TOP_PAD + 2 * TEXT_H + 18;
        let bottom_margin = TICK_LEN + LABEL_GAP + 2 * TEXT_H + 18;
        let right = (width - right_margin).max(left + 1);
        let bottom = (height - bottom_margin).max(top + 1);
        Self {
            x,
            y,
            left,
            top,
            right,
            bottom,
        }
    }

    fn x_px(&self, v: f64) -> i64 {
        self.left + (self.x.fraction(v) * (self.right - self.left) as f64).round() as i64
    }

    fn y_px(&self, v: f64) -> i64 {
        self.bottom - (self.y.fraction(v) * (self.bottom - self.top) as f64).round() as i64
    }

    fn to_px(&self, (x, y): (f64, f64)) -> (i64, i64) {
        (self.x_px(x), self.y_px(y))
    }

    /// Grid lines, tick marks and tick labels for both axes.
    fn draw_ticks(&self, img: &mut RgbImage) {
        for (value, label) in &self.x.ticks {
            let x = self.x_px(*value);
            if (self.left..=self.right).contains(&x) {
                fill_rect(img, x, self.top, x + 1, self.bottom, GRID);
                fill_rect(img, x, self.bottom, x + 1, self.bottom + TICK_LEN, AXIS);
                let label_y = self.bottom + TICK_LEN + LABEL_GAP;
                draw_text(img, x - text_width(label) / 2, label_y, label);
            }
        }
        for (value, label) in &self.y.ticks {
            let y = self.y_px(*value);
            if (self.top..=self.bottom).contains(&y) {
                fill_rect(img, self.left, y, self.right, y + 1, GRID);
                fill_rect(img, self.left - TICK_LEN, y, self.left, y + 1, AXIS);
                let label_x = self.left - TICK_LEN - LABEL_GAP - text_width(label);
                draw_text(img, label_x, y - TEXT_H / 2, label);
            }
        }
    }

    /// Legend box in the top-right corner of the plot area: swatch and name per series.
    fn draw_legend(&self, img: &mut RgbImage, series: &[Series]) {
        if series.is_empty() {
            return;
        }
        let (row_h, swatch) = (TEXT_H + 6, 18);
        let widest = series
            .iter()
            .map(|s| text_width(&s.name))
            .max()
            .unwrap_or(0);
        let x1 = self.right - 8;
        let x0 = x1 - (8 + swatch + 6 + widest + 8);
        let y0 = self.top + 8;
        let y1 = y0 + 6 + series.len() as i64 * row_h;
        fill_rect(img, x0, y0, x1, y1, WHITE);
        draw_box(img, x0, y0, x1, y1, LEGEND_BORDER);
        for (i, s) in series.iter().enumerate() {
            let y = y0 + 6 + i as i64 * row_h;
            let (sx, mid) = (x0 + 8, y + TEXT_H / 2);
            fill_rect(img, sx, mid - 1, sx + swatch, mid + 1, s.colour);
            let cx = sx + swatch / 2;
            fill_rect(img, cx - 2, mid - 2, cx + 3, mid + 3, s.colour);
            draw_text(img, sx + swatch + 6, y, &s.name);
        }
    }
}

fn glyph(c: char) -> Glyph {
    FONT.iter()
        .find(|entry| entry.0 == c)
        .map_or(UNKNOWN_GLYPH, |entry| entry.1)
}

fn text_width(text: &str) -> i64 {
    let n = text.chars().count() as i64;
    (n * ADVANCE - FONT_SCALE).max(0)
}

/// Draw `text` with its top-left corner at `(x, y)`.
pub(crate) fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str) {
    for (i, c) in text.chars().enumerate() {
        let gx = x + i as i64 * ADVANCE;
        if gx >= i64::from(img.width()) {
            break;
        }
        for (row, &bits) in glyph(c).iter().enumerate() {
            let py = y + row as i64 * FONT_SCALE;
            for col in 0..GLYPH_W {
                if (bits & (0x10u8 >> col)) != 0 {
                    let px = gx + col * FONT_SCALE;
                    fill_rect(img, px, py, px + FONT_SCALE, py + FONT_SCALE, TEXT);
                }
            }
        }
    }
}

/// Bresenham line drawn with a 2x2 brush, so it is 2 px wide.
fn draw_line(img: &mut RgbImage, from: (i64, i64), to: (i64, i64), colour: [u8; 3]) {
    let (mut x, mut y) = from;
    let dx = (to.0 - x).abs();
    let dy = -(to.1 - y).abs();
    let sx = if x < to.0 { 1 } else { -1 };
    let sy = if y < to.1 { 1 } else { -1 };
    let mut err = dx + dy;
    loop {
        fill_rect(img, x, y, x + 2, y + 2, colour);
        if (x, y) == to {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// One-pixel outline of the rectangle with inclusive corners `(x0, y0)` and `(x1, y1)`.
fn draw_box(img: &mut RgbImage, x0: i64, y0: i64, x1: i64, y1: i64, colour: [u8; 3]) {
    fill_rect(img, x0, y0, x1 + 1, y0 + 1, colour);
    fill_rect(img, x0, y1, x1 + 1, y1 + 1, colour);
    fill_rect(img, x0, y0, x0 + 1, y1 + 1, colour);
    fill_rect(img, x1, y0, x1 + 1, y1 + 1, colour);
}

/// Fill `x0..x1` x `y0..y1` (exclusive ends), clipped to the image.
fn fill_rect(img: &mut RgbImage, x0: i64, y0: i64, x1: i64, y1: i64, colour: [u8; 3]) {
    let (x1, y1) = (
        x1.min(i64::from(img.width())),
        y1.min(i64::from(img.height())),
    );
    for y in y0.max(0)..y1 {
        for x in x0.max(0)..x1 {
            put(img, x, y, colour);
        }
    }
}

/// Set one pixel; writes outside the image are ignored.
fn put(img: &mut RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if (0..i64::from(img.width())).contains(&x) && (0..i64::from(img.height())).contains(&y) {
        img.put_pixel(x as u32, y as u32, Rgb(colour));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * b.abs().max(1.0)
    }

    fn two_series_plot() -> Plot {
        Plot::new("loss vs step", "step", "loss")
            .series(
                "ours",
                [200, 30, 30],
                vec![(0.0, 0.0), (0.5, 0.5), (1.0, 1.0)],
            )
            .series("baseline", [30, 30, 200], vec![(0.0, 0.9), (1.0, 0.9)])
    }

    fn labels(ticks: &[(f64, String)]) -> Vec<&str> {
        ticks.iter().map(|t| t.1.as_str()).collect()
    }

    #[test]
    fn renders_requested_size() {
        let mut plot = two_series_plot();
        assert_eq!(plot.render().dimensions(), (800, 500));
        plot.width = 640;
        plot.height = 360;
        assert_eq!(plot.render().dimensions(), (640, 360));
    }

    #[test]
    fn series_colour_appears_inside_plot_area() {
        let plot = two_series_plot();
        let img = plot.render();
        let frame = Frame::fit(&plot, 800, 500);
        let (cx, cy) = frame.to_px((0.5, 0.5));
        assert!(cx > frame.left && cx < frame.right && cy > frame.top && cy < frame.bottom);
        assert_eq!(img.get_pixel(cx as u32, cy as u32).0, [200, 30, 30]);
        let inside = img
            .enumerate_pixels()
            .filter(|(x, y, p)| {
                let (x, y) = (i64::from(*x), i64::from(*y));
                let in_x = x > frame.left && x < frame.right;
                in_x && y > frame.top && y < frame.bottom && p.0 == [200, 30, 30]
            })
            .count();
        assert!(
            inside > 100,
            "only {inside} series pixels inside the plot area"
        );
    }

    #[test]
    fn degenerate_inputs_render_without_panicking() {
        let bad = vec![(f64::NAN, 1.0), (f64::INFINITY, f64::NAN)];
        let nan = Plot::new("nan", "x", "y").series("bad", PALETTE[0], bad);
        assert_eq!(nan.render().dimensions(), (800, 500));
        let empty = Plot::new("empty", "x", "y").log_x().log_y();
        assert_eq!(empty.render().dimensions(), (800, 500));
        let flat = Plot::new("flat", "x", "y").series("c", PALETTE[2], vec![(2.0, 3.0); 2]);
        assert_eq!(flat.render().dimensions(), (800, 500));
        let points = vec![
            (-1e308, -1.0),
            (1e308, 0.0),
            (5e-324, 5e-324),
            (f64::MAX, 1e308),
        ];
        let extreme = Plot::new("", "", "")
            .log_y()
            .series("extreme", PALETTE[1], points);
        assert_eq!(extreme.render().dimensions(), (800, 500));
        let mut tiny =
            Plot::new("tiny \u{2603}", "x", "y").series("p", PALETTE[3], vec![(1.0, 1.0)]);
        tiny.width = 0;
        tiny.height = 3;
        assert_eq!(tiny.render().dimensions(), (1, 3));
    }

    #[test]
    fn log_ticks_cover_the_decades() {
        let ticks = log_ticks(3, 6);
        assert_eq!(ticks.len(), 4);
        for ((value, _), want) in ticks.iter().zip([1e3, 1e4, 1e5, 1e6]) {
            assert!(close(*value, want), "{value} != {want}");
        }
        assert_eq!(labels(&ticks), ["1e3", "1e4", "1e5", "1e6"]);
        assert_eq!(Axis::fit(Scale::Log10, &[2e3, 5e5]).ticks.len(), 4);
        let short = Axis::fit(Scale::Log10, &[3.0, 7.0]);
        assert_eq!(labels(&short.ticks), ["1", "2", "5", "10"]);
    }

    #[test]
    fn linear_ticks_for_unit_range_include_both_ends() {
        let ticks = linear_ticks(0.0, 1.0);
        assert!((4..=7).contains(&ticks.len()), "{ticks:?}");
        assert!(ticks.iter().any(|&t| close(t, 0.0)));
        assert!(ticks.iter().any(|&t| close(t, 1.0)));
        let ticks = linear_ticks(0.0, 117.0);
        assert!(ticks.last().is_some_and(|&t| close(t, 120.0)), "{ticks:?}");
    }

    #[test]
    fn linear_labels_are_compact() {
        assert_eq!(linear_labels(&[0.2, 0.25, 0.3]), ["0.2", "0.25", "0.3"]);
        assert_eq!(
            linear_labels(&[0.0, 40.0, 80.0, 120.0]),
            ["0", "40", "80", "120"]
        );
        assert_eq!(
            linear_labels(&[0.0, 5e-5, 1e-4, 1.5e-4]),
            ["0", "5e-5", "1e-4", "1.5e-4"]
        );
        assert_eq!(
            labels(&Axis::fit(Scale::Linear, &[0.0, 2e5]).ticks)[1],
            "5e4"
        );
    }

    #[test]
    fn font_covers_required_characters_with_five_bit_rows() {
        let required =
            "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ .,-+_/():%=x^e";
        for c in required.chars() {
            assert!(FONT.iter().any(|entry| entry.0 == c), "missing glyph {c:?}");
        }
        for (c, rows) in FONT {
            assert!(
                rows.iter().all(|&r| r < 0x20),
                "glyph {c:?} is wider than 5 px"
            );
            assert!(
                *c == ' ' || rows.iter().any(|&r| r != 0),
                "glyph {c:?} is blank"
            );
            assert_eq!(
                FONT.iter().filter(|entry| entry.0 == *c).count(),
                1,
                "duplicate {c:?}"
            );
        }
        assert_eq!(glyph('\u{2603}'), UNKNOWN_GLYPH);
    }
}
