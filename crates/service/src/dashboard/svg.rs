//! The dashboard's figures, drawn here as SVG from the result document: the rig from
//! above with its drive, the residual histogram, residual bars and a vehicle's drift.
//!
//! Drawn on the server so that every figure is plain data → markup, unit-tested in Rust,
//! and the page needs no charting library. Every text that comes from a client (camera
//! ids, labels) is escaped; numbers are formatted here, never interpolated as markup.

use rigcal_core::geometry::{Mat3, Vec3};
use rigcal_core::result::{ExtrinsicValue, Histogram, ResultDocument};
use std::fmt::Write;

/// Colour-blind-safe categorical palette (Okabe–Ito), dark enough on white for 3:1 contrast.
pub const PALETTE: [&str; 7] = [
    "#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000",
];

/// XML text escaping for element content and attribute values.
pub use rigcal_core::xml::escape as esc;

/// An SVG document with an accessible name (`<title>`) and a longer description.
fn open(w: f64, h: f64, title: &str, desc: &str) -> String {
    format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 {w} {h}\" width=\"{w}\" height=\"{h}\" role=\"img\" aria-labelledby=\"t d\" font-family=\"system-ui, sans-serif\" font-size=\"12\"><title id=\"t\">{}</title><desc id=\"d\">{}</desc><rect width=\"{w}\" height=\"{h}\" fill=\"#fff\"/>",
        esc(title),
        esc(desc)
    )
}

/// "Nice" tick step for a range (1, 2 or 5 × 10^k), about `n` ticks.
fn tick_step(range: f64, n: f64) -> f64 {
    if !(range.is_finite() && range > 0.0) {
        return 1.0;
    }
    let raw = range / n;
    let mag = 10f64.powf(raw.log10().floor());
    let f = raw / mag;
    mag * if f < 1.5 {
        1.0
    } else if f < 3.5 {
        2.0
    } else if f < 7.5 {
        5.0
    } else {
        10.0
    }
}

/// The multiples of `step` in `[lo, hi]`.
fn ticks(lo: f64, hi: f64, step: f64) -> impl Iterator<Item = f64> {
    std::iter::successors(Some((lo / step).ceil() * step), move |v| Some(v + step))
        .take_while(move |v| *v <= hi + 1e-9 * step)
}

fn fmt_tick(v: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).clamp(0.0, 6.0) as usize;
    // A tick at zero reached by adding steps is a rounding residue: never "-0.0".
    let v = if v.abs() < 1e-9 * step { 0.0 } else { v };
    format!("{v:.decimals$}")
}

/// A plot area: data ranges mapped to a pixel rectangle (y up).
struct Frame {
    x0: f64,
    y0: f64,
    w: f64,
    h: f64,
    xmin: f64,
    xmax: f64,
    ymin: f64,
    ymax: f64,
    /// Ticks on whole numbers only (counts, calibration numbers).
    integer_x: bool,
}

impl Frame {
    fn px(&self, x: f64) -> f64 {
        self.x0 + (x - self.xmin) / (self.xmax - self.xmin) * self.w
    }
    fn py(&self, y: f64) -> f64 {
        self.y0 + self.h - (y - self.ymin) / (self.ymax - self.ymin) * self.h
    }
    /// Axes with ticks and labels.
    fn axes(&self, svg: &mut String, xlabel: &str, ylabel: &str, xticks: bool) {
        let (x1, y1) = (self.x0 + self.w, self.y0 + self.h);
        let _ = write!(
            svg,
            "<g stroke=\"#444\" fill=\"none\"><line x1=\"{:.1}\" y1=\"{y1:.1}\" x2=\"{x1:.1}\" y2=\"{y1:.1}\"/><line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{y1:.1}\"/></g>",
            self.x0, self.x0, self.y0, self.x0
        );
        let ys = tick_step(self.ymax - self.ymin, 4.0);
        for v in ticks(self.ymin, self.ymax, ys) {
            let y = self.py(v);
            let _ = write!(
                svg,
                "<line x1=\"{:.1}\" y1=\"{y:.1}\" x2=\"{x1:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/><text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\" fill=\"#333\">{}</text>",
                self.x0,
                self.x0 - 4.0,
                y + 4.0,
                fmt_tick(v, ys)
            );
        }
        if xticks {
            let mut xs = tick_step(self.xmax - self.xmin, 6.0);
            if self.integer_x {
                xs = xs.max(1.0);
            }
            for v in ticks(self.xmin, self.xmax, xs) {
                let x = self.px(v);
                let _ = write!(
                    svg,
                    "<line x1=\"{x:.1}\" y1=\"{y1:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#444\"/><text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\" fill=\"#333\">{}</text>",
                    y1 + 4.0,
                    y1 + 16.0,
                    fmt_tick(v, xs)
                );
            }
        }
        let _ = write!(
            svg,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\" fill=\"#333\">{}</text><text transform=\"translate({:.1} {:.1}) rotate(-90)\" text-anchor=\"middle\" fill=\"#333\">{}</text>",
            self.x0 + self.w / 2.0,
            y1 + 32.0,
            esc(xlabel),
            self.x0 - 50.0,
            self.y0 + self.h / 2.0,
            esc(ylabel)
        );
    }
}

/// The plane the rig is drawn in, seen from above: `right` and `forward` span the ground,
/// `up` is its normal, all in the reference camera's frame.
///
/// Up is the motion-plane normal when the drive was planar or turned about one axis (the
/// ground, measured), else the reference camera's −y (cameras are mounted upright).
/// Forward is the reference camera's optical axis on the ground.
pub fn ground_basis(doc: &ResultDocument) -> (Vec3, Vec3, Vec3) {
    let minus_y = Vec3::new(0.0, -1.0, 0.0);
    let mut up = match &doc.singularity {
        Some(s) if s.motion_class == "planar" || s.motion_class == "single_axis" => {
            let a = Vec3::new(s.axis[0], s.axis[1], s.axis[2]);
            if a.norm() > 0.5 {
                a.normalize()
            } else {
                minus_y
            }
        }
        _ => minus_y,
    };
    if up.dot(&minus_y) < 0.0 {
        up = -up;
    }
    let z = Vec3::new(0.0, 0.0, 1.0);
    let mut forward = z - up * up.dot(&z);
    if forward.norm() < 1e-6 {
        let x = Vec3::new(1.0, 0.0, 0.0);
        forward = x - up * up.dot(&x);
    }
    let forward = forward.normalize();
    let right = forward.cross(&up);
    (right, forward, up)
}

fn rot_of(q: [f64; 4]) -> Mat3 {
    nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
        .to_rotation_matrix()
        .into_inner()
}

/// Top view of the rig (each camera an oriented frustum with its id) beside the drive
/// (the reference camera's path, a heading tick every few frames).
pub fn rig_top_view(doc: &ResultDocument) -> String {
    let (right, forward, _) = ground_basis(doc);
    let ground = |p: Vec3| (p.dot(&right), p.dot(&forward));
    let cams: Vec<&ExtrinsicValue> = doc.extrinsics.iter().map(|e| &e.value).collect();
    let (w, h) = (720.0, 360.0);
    let mut svg = open(
        w,
        h,
        "Rig and drive, top view",
        &format!(
            "Left: the {} cameras seen from above, forward up, each a frustum along its optical axis. Right: the reference camera's path over {} frames.",
            cams.len(),
            doc.trajectory.len()
        ),
    );
    // Left panel: cameras.
    let centres: Vec<(f64, f64)> = cams
        .iter()
        .map(|c| {
            ground(Vec3::new(
                c.translation[0],
                c.translation[1],
                c.translation[2],
            ))
        })
        .collect();
    let extent = centres
        .iter()
        .map(|(a, b)| a.abs().max(b.abs()))
        .fold(0.0, f64::max)
        .max(0.05);
    let half = extent * 1.45;
    let panel = Frame {
        x0: 60.0,
        y0: 30.0,
        w: 280.0,
        h: 280.0,
        xmin: -half,
        xmax: half,
        ymin: -half,
        ymax: half,
        integer_x: false,
    };
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"18\" text-anchor=\"middle\" font-weight=\"600\">Rig (m), forward ↑</text>",
        panel.x0 + panel.w / 2.0
    );
    panel.axes(&mut svg, "right (m)", "forward (m)", true);
    let len = half * 0.28;
    for (i, (c, (cx, cy))) in cams.iter().zip(&centres).enumerate() {
        let r = rot_of(c.quaternion_wxyz);
        let colour = PALETTE[i % PALETTE.len()];
        let centre = Vec3::new(c.translation[0], c.translation[1], c.translation[2]);
        let ray = |dx: f64| {
            let d = r * Vec3::new(dx, 0.0, 1.0);
            ground(centre + d.normalize() * len)
        };
        let (l, m, rr) = (ray(-0.6), ray(0.0), ray(0.6));
        let _ = write!(
            svg,
            "<g><title>{id}</title><polygon points=\"{:.1},{:.1} {:.1},{:.1} {:.1},{:.1}\" fill=\"{colour}\" fill-opacity=\"0.25\" stroke=\"{colour}\" stroke-width=\"1.5\"/><line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"{colour}\" stroke-width=\"2\"/><circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3.5\" fill=\"{colour}\"/><text x=\"{:.1}\" y=\"{:.1}\" fill=\"#111\" class=\"cam-label\">{id}</text></g>",
            panel.px(*cx),
            panel.py(*cy),
            panel.px(l.0),
            panel.py(l.1),
            panel.px(rr.0),
            panel.py(rr.1),
            panel.px(*cx),
            panel.py(*cy),
            panel.px(m.0),
            panel.py(m.1),
            panel.px(*cx),
            panel.py(*cy),
            panel.px(*cx) + 6.0,
            panel.py(*cy) - 6.0,
            id = esc(&c.camera),
        );
    }
    // Right panel: the drive.
    let path: Vec<(f64, f64)> = doc
        .trajectory
        .iter()
        .map(|p| {
            ground(Vec3::new(
                p.translation[0],
                p.translation[1],
                p.translation[2],
            ))
        })
        .collect();
    let (mut xmin, mut xmax, mut ymin, mut ymax) = (-0.5f64, 0.5f64, -0.5f64, 0.5f64);
    for (x, y) in &path {
        xmin = xmin.min(*x);
        xmax = xmax.max(*x);
        ymin = ymin.min(*y);
        ymax = ymax.max(*y);
    }
    // Equal scale on both axes: pad the shorter range.
    let span = (xmax - xmin).max(ymax - ymin) * 1.1;
    let (cx, cy) = ((xmin + xmax) / 2.0, (ymin + ymax) / 2.0);
    let drive = Frame {
        x0: 420.0,
        y0: 30.0,
        w: 280.0,
        h: 280.0,
        xmin: cx - span / 2.0,
        xmax: cx + span / 2.0,
        ymin: cy - span / 2.0,
        ymax: cy + span / 2.0,
        integer_x: false,
    };
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"18\" text-anchor=\"middle\" font-weight=\"600\">Drive (m), {} frames</text>",
        drive.x0 + drive.w / 2.0,
        path.len()
    );
    drive.axes(&mut svg, "right (m)", "forward (m)", true);
    if path.is_empty() {
        let _ = write!(
            svg,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\" fill=\"#555\">no drive: this method does not move the rig</text>",
            drive.x0 + drive.w / 2.0,
            drive.y0 + drive.h / 2.0
        );
    } else {
        let pts: Vec<String> = path
            .iter()
            .map(|(x, y)| format!("{:.1},{:.1}", drive.px(*x), drive.py(*y)))
            .collect();
        let _ = write!(
            svg,
            "<polyline points=\"{}\" fill=\"none\" stroke=\"{}\" stroke-width=\"2\"/>",
            pts.join(" "),
            PALETTE[0]
        );
        let every = (path.len() / 12).max(1);
        let tick = span * 0.04;
        for (k, p) in doc.trajectory.iter().enumerate().step_by(every) {
            let r = rot_of(p.quaternion_wxyz);
            let o = Vec3::new(p.translation[0], p.translation[1], p.translation[2]);
            let (ax, ay) = path[k];
            let (bx, by) = ground(o + r * Vec3::new(0.0, 0.0, 1.0) * tick * 2.0);
            let _ = write!(
                svg,
                "<g><title>frame {}</title><circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{}\"/><line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"{}\" stroke-width=\"1.5\"/></g>",
                p.frame,
                drive.px(ax),
                drive.py(ay),
                PALETTE[1],
                drive.px(ax),
                drive.py(ay),
                drive.px(bx),
                drive.py(by),
                PALETTE[1]
            );
        }
    }
    svg.push_str("</svg>");
    svg
}

/// Histogram of the residuals (px).
pub fn residual_histogram(h: &Histogram) -> String {
    let (w, hh) = (520.0, 240.0);
    let total: usize = h.counts.iter().sum();
    let mut svg = open(
        w,
        hh,
        "Residual histogram",
        &format!(
            "{total} reprojection residuals in {} bins, pixels.",
            h.counts.len()
        ),
    );
    let (xmin, xmax) = match (h.edges_px.first(), h.edges_px.last()) {
        (Some(a), Some(b)) if b > a => (*a, *b),
        _ => (0.0, 1.0),
    };
    let ymax = h.counts.iter().copied().max().unwrap_or(0).max(1) as f64 * 1.05;
    let f = Frame {
        x0: 64.0,
        y0: 12.0,
        w: w - 80.0,
        h: hh - 56.0,
        xmin,
        xmax,
        ymin: 0.0,
        ymax,
        integer_x: false,
    };
    f.axes(&mut svg, "residual (px)", "observations", true);
    for (i, c) in h.counts.iter().enumerate() {
        let (Some(a), Some(b)) = (h.edges_px.get(i), h.edges_px.get(i + 1)) else {
            break;
        };
        let (x, y) = (f.px(*a), f.py(*c as f64));
        let _ = write!(
            svg,
            "<rect x=\"{x:.1}\" y=\"{y:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{}\"><title>{a:.3}–{b:.3} px: {c}</title></rect>",
            (f.px(*b) - x - 1.0).max(0.5),
            f.py(0.0) - y,
            PALETTE[0]
        );
    }
    svg.push_str("</svg>");
    svg
}

/// One bar per item (RMS px), with the item's p95 as a tick: per camera or per frame.
pub fn residual_bars(title: &str, xlabel: &str, items: &[(String, f64, f64)]) -> String {
    let (w, h) = (520.0, 240.0);
    let mut svg = open(
        w,
        h,
        title,
        &format!(
            "Residual RMS (bar) and 95th percentile (tick) in pixels for {} {}.",
            items.len(),
            xlabel
        ),
    );
    let ymax = items
        .iter()
        .map(|(_, r, p)| r.max(*p))
        .fold(0.0, f64::max)
        .max(1e-3)
        * 1.1;
    let f = Frame {
        x0: 64.0,
        y0: 12.0,
        w: w - 80.0,
        h: h - 56.0,
        xmin: 0.0,
        xmax: items.len().max(1) as f64,
        ymin: 0.0,
        ymax,
        integer_x: true,
    };
    f.axes(&mut svg, xlabel, "px", false);
    let labels = items.len() <= 24;
    for (i, (name, rms, p95)) in items.iter().enumerate() {
        let (x, bw) = (f.px(i as f64), f.w / items.len() as f64);
        let y = f.py(*rms);
        let _ = write!(
            svg,
            "<g><title>{}: RMS {rms:.3} px, p95 {p95:.3} px</title><rect x=\"{:.1}\" y=\"{y:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{}\"/><line x1=\"{:.1}\" x2=\"{:.1}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"{}\" stroke-width=\"2\"/></g>",
            esc(name),
            x + bw * 0.15,
            bw * 0.7,
            f.py(0.0) - y,
            PALETTE[0],
            x + bw * 0.1,
            x + bw * 0.9,
            f.py(*p95),
            f.py(*p95),
            PALETTE[1]
        );
        if labels {
            let _ = write!(
                svg,
                "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\" fill=\"#333\">{}</text>",
                x + bw / 2.0,
                f.py(0.0) + 14.0,
                esc(name)
            );
        }
    }
    svg.push_str("</svg>");
    svg
}

/// One camera's change between consecutive accepted calibrations.
pub struct DriftSeries {
    pub camera: String,
    /// (calibration index in the history, translation change mm, rotation change deg).
    pub points: Vec<(usize, f64, f64)>,
}

/// A vehicle's drift: per camera, the change from the previous accepted calibration,
/// translation (mm) above and rotation (deg) below, against the calibration's position
/// in the history.
pub fn drift_chart(series: &[DriftSeries], calibrations: usize) -> String {
    let (w, h) = (640.0, 380.0);
    let mut svg = open(
        w,
        h,
        "Drift between calibrations",
        &format!(
            "Change of each of {} cameras from the previous accepted calibration over {calibrations} calibrations: translation in millimetres (top), rotation in degrees (bottom).",
            series.len()
        ),
    );
    let xmax = calibrations.max(2) as f64 - 0.5;
    for (panel, (label, pick)) in [
        ("translation change (mm)", 0usize),
        ("rotation change (deg)", 1usize),
    ]
    .into_iter()
    .enumerate()
    {
        let value = |p: &(usize, f64, f64)| if pick == 0 { p.1 } else { p.2 };
        let ymax = series
            .iter()
            .flat_map(|s| s.points.iter().map(value))
            .fold(0.0, f64::max)
            .max(1e-3)
            * 1.15;
        let f = Frame {
            x0: 76.0,
            y0: 14.0 + panel as f64 * 170.0,
            w: w - 196.0,
            h: 120.0,
            xmin: -0.5,
            xmax,
            ymin: 0.0,
            ymax,
            integer_x: true,
        };
        f.axes(
            &mut svg,
            if panel == 1 { "calibration #" } else { "" },
            label,
            true,
        );
        for (i, s) in series.iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            let pts: Vec<String> = s
                .points
                .iter()
                .map(|p| format!("{:.1},{:.1}", f.px(p.0 as f64), f.py(value(p))))
                .collect();
            if pts.len() > 1 {
                let _ = write!(
                    svg,
                    "<polyline points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.5\"/>",
                    pts.join(" ")
                );
            }
            for p in &s.points {
                let _ = write!(
                    svg,
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{colour}\"><title>{} #{}: {:.3}</title></circle>",
                    f.px(p.0 as f64),
                    f.py(value(p)),
                    esc(&s.camera),
                    p.0,
                    value(p)
                );
            }
        }
    }
    if series.is_empty() {
        let _ = write!(
            svg,
            "<text x=\"{:.1}\" y=\"160\" text-anchor=\"middle\" fill=\"#555\">no drift yet: it needs two accepted calibrations</text>",
            76.0 + (w - 196.0) / 2.0
        );
    }
    for (i, s) in series.iter().enumerate() {
        let y = 30.0 + i as f64 * 18.0;
        let _ = write!(
            svg,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"12\" height=\"12\" fill=\"{}\"/><text x=\"{:.1}\" y=\"{:.1}\" fill=\"#111\">{}</text>",
            w - 110.0,
            y - 10.0,
            PALETTE[i % PALETTE.len()],
            w - 92.0,
            y,
            esc(&s.camera)
        );
    }
    svg.push_str("</svg>");
    svg
}

/// One camera of a vehicle model's fleet: every vehicle's latest deviation from the
/// nominal rig on each of the six axes (a dot per vehicle, outliers larger and in
/// vermilion, the fleet median as a line, the band of ±`z` spreads shaded), and below,
/// the drift of the fleet median per period.
pub fn fleet_chart(
    camera: &str,
    stats: &[crate::fleet::AxisStats],
    latest: &[Vec<(f64, bool)>; 6],
    z: f64,
    drift: &[&crate::fleet::DriftSeries],
) -> String {
    let (w, strip, gap) = (640.0, 34.0, 22.0);
    let top = 10.0;
    let drift_top = top + 6.0 * (strip + gap) + 10.0;
    let h = drift_top + 2.0 * 150.0 + 10.0;
    let n = latest[0].len();
    let mut svg = open(
        w,
        h,
        &format!("Fleet: camera {camera}"),
        &format!(
            "Camera {camera}: the latest accepted calibration of each of {n} vehicles as its deviation from the nominal rig, translation in millimetres and rotation in degrees per reference axis; outliers beyond {z} robust spreads marked; then the fleet median per period."
        ),
    );
    let (x0, pw) = (110.0, w - 130.0);
    for (a, st) in stats.iter().enumerate().take(6) {
        let y0 = top + a as f64 * (strip + gap);
        let vals = &latest[a];
        let band = (st.median - z * st.spread, st.median + z * st.spread);
        let (mut lo, mut hi) = vals
            .iter()
            .fold((band.0, band.1), |(l, h), &(v, _)| (l.min(v), h.max(v)));
        if !(lo.is_finite() && hi.is_finite()) {
            (lo, hi) = (-1.0, 1.0);
        }
        let pad = ((hi - lo) * 0.05).max(1e-6);
        let (lo, hi) = (lo - pad, hi + pad);
        let px = |v: f64| x0 + (v - lo) / (hi - lo) * pw;
        let _ = write!(
            svg,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\" fill=\"#111\">{} ({})</text>",
            x0 - 8.0,
            y0 + strip / 2.0 + 4.0,
            st.axis,
            st.unit
        );
        if band.0.is_finite() && band.1.is_finite() {
            let _ = write!(
                svg,
                "<rect x=\"{:.1}\" y=\"{y0:.1}\" width=\"{:.1}\" height=\"{strip}\" fill=\"#eef3f8\"/>",
                px(band.0),
                (px(band.1) - px(band.0)).max(0.5)
            );
        }
        if st.median.is_finite() {
            let _ = write!(
                svg,
                "<line x1=\"{0:.1}\" y1=\"{y0:.1}\" x2=\"{0:.1}\" y2=\"{1:.1}\" stroke=\"#0072B2\" stroke-width=\"2\"><title>median {2:.4} {3}</title></line>",
                px(st.median),
                y0 + strip,
                st.median,
                st.unit
            );
        }
        let _ = write!(
            svg,
            "<line x1=\"{x0:.1}\" y1=\"{0:.1}\" x2=\"{1:.1}\" y2=\"{0:.1}\" stroke=\"#444\"/>",
            y0 + strip,
            x0 + pw
        );
        let step = tick_step(hi - lo, 6.0);
        for v in ticks(lo, hi, step) {
            let _ = write!(
                svg,
                "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\" fill=\"#333\" font-size=\"10\">{}</text>",
                px(v),
                y0 + strip + 12.0,
                fmt_tick(v, step)
            );
        }
        for (i, &(v, out)) in vals.iter().enumerate() {
            // Deterministic jitter so that equal values stay visible as a column.
            let jy = y0 + 4.0 + ((i * 7919) % 97) as f64 / 96.0 * (strip - 8.0);
            let (r, colour) = if out { (4.0, "#D55E00") } else { (2.0, "#555") };
            let _ = write!(
                svg,
                "<circle cx=\"{:.1}\" cy=\"{jy:.1}\" r=\"{r}\" fill=\"{colour}\"{}/>",
                px(v),
                if out { " class=\"outlier\"" } else { "" }
            );
        }
    }
    for (panel, unit) in ["mm", "deg"].into_iter().enumerate() {
        let series: Vec<&&crate::fleet::DriftSeries> =
            drift.iter().filter(|d| d.unit == unit).collect();
        let pts = series.iter().flat_map(|d| d.points.iter());
        let (xmin, xmax, ymin, ymax) = pts.fold(
            (
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
            ),
            |(a, b, c, d), p| {
                let x = p.from as f64 / 86_400_000.0;
                (a.min(x), b.max(x), c.min(p.median), d.max(p.median))
            },
        );
        let (xmin, xmax) = if xmin.is_finite() {
            (xmin - 1.0, xmax + 1.0)
        } else {
            (0.0, 1.0)
        };
        let (ymin, ymax) = if ymin.is_finite() {
            let pad = ((ymax - ymin) * 0.15).max(1e-4);
            (ymin - pad, ymax + pad)
        } else {
            (-1.0, 1.0)
        };
        let f = Frame {
            x0: 76.0,
            y0: drift_top + panel as f64 * 150.0,
            w: w - 196.0,
            h: 100.0,
            xmin,
            xmax,
            ymin,
            ymax,
            integer_x: true,
        };
        f.axes(
            &mut svg,
            if panel == 1 {
                "period start (days since 1970-01-01)"
            } else {
                ""
            },
            &format!("median ({unit})"),
            true,
        );
        for (i, d) in series.iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            let line: Vec<String> = d
                .points
                .iter()
                .map(|p| {
                    format!(
                        "{:.1},{:.1}",
                        f.px(p.from as f64 / 86_400_000.0),
                        f.py(p.median)
                    )
                })
                .collect();
            let _ = write!(
                svg,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.5\"/>",
                line.join(" ")
            );
            for p in &d.points {
                let _ = write!(
                    svg,
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"2.5\" fill=\"{colour}\"><title>{} {}: median {:.4} {unit} of {}</title></circle>",
                    f.px(p.from as f64 / 86_400_000.0),
                    f.py(p.median),
                    esc(camera),
                    d.axis,
                    p.median,
                    p.count
                );
            }
            let _ = write!(
                svg,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"12\" height=\"12\" fill=\"{colour}\"/><text x=\"{:.1}\" y=\"{:.1}\" fill=\"#111\">{}</text>",
                w - 110.0,
                f.y0 + 6.0 + i as f64 * 18.0,
                w - 92.0,
                f.y0 + 16.0 + i as f64 * 18.0,
                d.axis
            );
        }
    }
    svg.push_str("</svg>");
    svg
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escaping_keeps_markup_out() {
        assert_eq!(esc("<script>&\"'"), "&lt;script&gt;&amp;&quot;&#39;");
        let h = residual_bars(
            "t",
            "cameras",
            &[("<b>x</b>".into(), 0.5, 0.9), ("y".into(), 0.2, 0.3)],
        );
        assert!(!h.contains("<b>"));
        assert!(h.contains("&lt;b&gt;x&lt;/b&gt;"));
    }

    #[test]
    fn ticks_are_round() {
        assert_eq!(tick_step(10.0, 5.0), 2.0);
        assert_eq!(tick_step(0.7, 4.0), 0.2);
        assert_eq!(tick_step(0.0, 4.0), 1.0);
        assert_eq!(fmt_tick(0.4, 0.2), "0.4");
        assert_eq!(fmt_tick(20.0, 5.0), "20");
        assert_eq!(fmt_tick(-0.1 + 0.1, 0.1), "0.0");
        assert_eq!(fmt_tick(-1e-17, 0.2), "0.0");
    }

    #[test]
    fn histogram_has_one_bar_per_bin_at_its_height() {
        let h = Histogram {
            edges_px: vec![0.0, 0.5, 1.0, 1.5],
            counts: vec![10, 5, 0],
        };
        let svg = residual_histogram(&h);
        assert_eq!(svg.matches("<rect x=").count(), 3);
        assert!(svg.contains("0.000–0.500 px: 10"));
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>"));
    }

    #[test]
    fn fleet_chart_marks_outliers_and_draws_every_vehicle() {
        use crate::fleet::{AxisStats, DriftPoint, DriftSeries as Fleet};
        let stats: Vec<AxisStats> = crate::fleet::AXES
            .iter()
            .map(|&(axis, unit)| AxisStats {
                axis,
                unit,
                median: 0.0,
                spread: 1.0,
                count: 4,
            })
            .collect();
        let col = vec![(0.1, false), (-0.4, false), (0.3, false), (9.0, true)];
        let latest: [Vec<(f64, bool)>; 6] = std::array::from_fn(|_| col.clone());
        let drift: Vec<Fleet> = crate::fleet::AXES
            .iter()
            .map(|&(axis, unit)| Fleet {
                camera: "rear".into(),
                axis,
                unit,
                points: vec![
                    DriftPoint {
                        from: 0,
                        median: 0.1,
                        count: 2,
                    },
                    DriftPoint {
                        from: 604_800_000,
                        median: 0.2,
                        count: 2,
                    },
                ],
            })
            .collect();
        let refs: Vec<&Fleet> = drift.iter().collect();
        let svg = fleet_chart("<rear>", &stats, &latest, 5.0, &refs);
        assert_eq!(svg.matches("class=\"outlier\"").count(), 6);
        // 4 vehicles × 6 axes, plus 2 periods × 6 drift series.
        assert_eq!(svg.matches("<circle").count(), 24 + 12);
        assert!(svg.contains("&lt;rear&gt;") && !svg.contains("<rear>"));
        assert_eq!(svg.matches("<polyline").count(), 6);
    }

    #[test]
    fn drift_chart_draws_each_camera() {
        let s = vec![
            DriftSeries {
                camera: "front".into(),
                points: vec![(1, 0.5, 0.01), (2, 1.5, 0.02)],
            },
            DriftSeries {
                camera: "rear".into(),
                points: vec![(1, 0.2, 0.03)],
            },
        ];
        let svg = drift_chart(&s, 3);
        // Two panels × three points, each with a tooltip.
        assert_eq!(svg.matches("<circle").count(), 6);
        assert_eq!(svg.matches("<polyline").count(), 2);
        assert!(svg.contains(">front</text>") && svg.contains(">rear</text>"));
    }
}
