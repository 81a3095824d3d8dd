//! Minimal SVG charts (line charts with optional log axes, grouped bar charts) for convergence
//! curves and comparison reports. No dependencies: the output is plain SVG 1.1 text.

use std::fmt::Write;

const W: f64 = 720.0;
const H: f64 = 440.0;
const LEFT: f64 = 80.0;
const RIGHT: f64 = 170.0;
const TOP: f64 = 40.0;
const BOTTOM: f64 = 60.0;
const COLORS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
];

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// An axis mapping data values to pixels.
struct Axis {
    lo: f64,
    hi: f64,
    log: bool,
    p0: f64,
    p1: f64,
}

impl Axis {
    fn new(values: impl Iterator<Item = f64>, log: bool, p0: f64, p1: f64) -> Axis {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for v in values.filter(|v| v.is_finite() && (!log || *v > 0.0)) {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        if !lo.is_finite() {
            (lo, hi) = if log { (1.0, 10.0) } else { (0.0, 1.0) };
        }
        if log {
            lo = 10f64.powf(lo.log10().floor());
            hi = 10f64.powf(hi.log10().ceil());
            if hi <= lo {
                hi = lo * 10.0;
            }
        } else {
            if lo > 0.0 {
                lo = 0.0;
            }
            if hi <= lo {
                hi = lo + 1.0;
            }
            hi *= 1.05;
        }
        Axis {
            lo,
            hi,
            log,
            p0,
            p1,
        }
    }

    fn map(&self, v: f64) -> f64 {
        let t = if self.log {
            (v.max(self.lo * 1e-3).log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        };
        self.p0 + t * (self.p1 - self.p0)
    }

    fn ticks(&self) -> Vec<f64> {
        if self.log {
            let mut t = Vec::new();
            let mut v = self.lo;
            while v <= self.hi * 1.0001 {
                t.push(v);
                v *= 10.0;
            }
            t
        } else {
            (0..=5)
                .map(|k| self.lo + (self.hi - self.lo) * k as f64 / 5.0)
                .collect()
        }
    }
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 1e4 || v.abs() < 1e-2 {
        format!("{v:.0e}")
    } else if v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

fn frame(out: &mut String, title: &str, x_label: &str, y_label: &str) {
    let _ = write!(
        out,
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="12"><rect width="{W}" height="{H}" fill="white"/><text x="{}" y="22" text-anchor="middle" font-size="15">{}</text><text x="{}" y="{}" text-anchor="middle">{}</text><text transform="translate(18 {}) rotate(-90)" text-anchor="middle">{}</text>"##,
        (LEFT + W - RIGHT) / 2.0,
        esc(title),
        (LEFT + W - RIGHT) / 2.0,
        H - 15.0,
        esc(x_label),
        (TOP + H - BOTTOM) / 2.0,
        esc(y_label)
    );
}

fn axes(out: &mut String, xa: &Axis, ya: &Axis, x_labels: Option<&[String]>) {
    let (x0, x1, y0, y1) = (LEFT, W - RIGHT, H - BOTTOM, TOP);
    let _ = write!(
        out,
        r##"<rect x="{x0}" y="{y1}" width="{}" height="{}" fill="none" stroke="#444"/>"##,
        x1 - x0,
        y0 - y1
    );
    for t in ya.ticks() {
        let y = ya.map(t);
        let _ = write!(
            out,
            r##"<line x1="{x0}" x2="{x1}" y1="{y:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
            x0 - 6.0,
            y + 4.0,
            fmt_tick(t)
        );
    }
    if let Some(labels) = x_labels {
        let n = labels.len().max(1) as f64;
        for (i, l) in labels.iter().enumerate() {
            let x = x0 + (i as f64 + 0.5) * (x1 - x0) / n;
            let _ = write!(
                out,
                r##"<text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
                y0 + 18.0,
                esc(l)
            );
        }
    } else {
        for t in xa.ticks() {
            let x = xa.map(t);
            let _ = write!(
                out,
                r##"<line x1="{x:.1}" x2="{x:.1}" y1="{y1}" y2="{y0}" stroke="#eee"/><text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
                y0 + 18.0,
                fmt_tick(t)
            );
        }
    }
}

fn legend(out: &mut String, names: &[&str]) {
    for (i, n) in names.iter().enumerate() {
        let y = TOP + 10.0 + 20.0 * i as f64;
        let x = W - RIGHT + 15.0;
        let _ = write!(
            out,
            r##"<rect x="{x}" y="{}" width="14" height="10" fill="{}"/><text x="{}" y="{}">{}</text>"##,
            y - 9.0,
            COLORS[i % COLORS.len()],
            x + 20.0,
            y,
            esc(n)
        );
    }
}

/// A line chart of `series` (name, points). Points with non-finite or (on log axes)
/// non-positive coordinates are skipped.
pub fn line_chart(
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
    log_x: bool,
    log_y: bool,
) -> String {
    let ok = |(x, y): &(f64, f64)| {
        x.is_finite() && y.is_finite() && (!log_x || *x > 0.0) && (!log_y || *y > 0.0)
    };
    let xa = Axis::new(
        series
            .iter()
            .flat_map(|s| s.1.iter().filter(|p| ok(p)).map(|p| p.0)),
        log_x,
        LEFT,
        W - RIGHT,
    );
    let ya = Axis::new(
        series
            .iter()
            .flat_map(|s| s.1.iter().filter(|p| ok(p)).map(|p| p.1)),
        log_y,
        H - BOTTOM,
        TOP,
    );
    let mut out = String::new();
    frame(&mut out, title, x_label, y_label);
    axes(&mut out, &xa, &ya, None);
    for (i, (_, pts)) in series.iter().enumerate() {
        let c = COLORS[i % COLORS.len()];
        let p: Vec<String> = pts
            .iter()
            .filter(|p| ok(p))
            .map(|&(x, y)| format!("{:.1},{:.1}", xa.map(x), ya.map(y)))
            .collect();
        if p.is_empty() {
            continue;
        }
        let _ = write!(
            out,
            r##"<polyline points="{}" fill="none" stroke="{c}" stroke-width="2"/>"##,
            p.join(" ")
        );
        for q in &p {
            let (x, y) = q.split_once(',').unwrap_or(("0", "0"));
            let _ = write!(out, r##"<circle cx="{x}" cy="{y}" r="3" fill="{c}"/>"##);
        }
    }
    let names: Vec<&str> = series.iter().map(|s| s.0.as_str()).collect();
    legend(&mut out, &names);
    out.push_str("</svg>\n");
    out
}

/// A grouped bar chart: one group per category, one bar per series; an optional horizontal
/// reference line (e.g. 1.0 for ratios).
pub fn bar_chart(
    title: &str,
    y_label: &str,
    categories: &[String],
    series: &[(String, Vec<f64>)],
    reference: Option<f64>,
) -> String {
    let ya = Axis::new(
        series
            .iter()
            .flat_map(|s| s.1.iter().copied())
            .chain(reference),
        false,
        H - BOTTOM,
        TOP,
    );
    let xa = Axis::new([0.0, 1.0].into_iter(), false, LEFT, W - RIGHT);
    let mut out = String::new();
    frame(&mut out, title, "", y_label);
    axes(&mut out, &xa, &ya, Some(categories));
    let n = categories.len().max(1) as f64;
    let group = (W - RIGHT - LEFT) / n;
    let k = series.len().max(1) as f64;
    let bw = group * 0.8 / k;
    for (j, (_, vals)) in series.iter().enumerate() {
        for (i, v) in vals.iter().enumerate() {
            if !v.is_finite() {
                continue;
            }
            let x = LEFT + i as f64 * group + group * 0.1 + j as f64 * bw;
            let (ya0, yv) = (ya.map(0.0f64.max(ya.lo)), ya.map(*v));
            let _ = write!(
                out,
                r##"<rect x="{x:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{}"><title>{}</title></rect>"##,
                yv.min(ya0),
                bw * 0.95,
                (ya0 - yv).abs(),
                COLORS[j % COLORS.len()],
                fmt_tick(*v)
            );
        }
    }
    if let Some(r) = reference {
        let y = ya.map(r);
        let _ = write!(
            out,
            r##"<line x1="{LEFT}" x2="{}" y1="{y:.1}" y2="{y:.1}" stroke="#000" stroke-dasharray="4 3"/>"##,
            W - RIGHT
        );
    }
    let names: Vec<&str> = series.iter().map(|s| s.0.as_str()).collect();
    legend(&mut out, &names);
    out.push_str("</svg>\n");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_are_well_formed_svg() {
        let s = line_chart(
            "relMSE <vs> spp",
            "spp",
            "relMSE",
            &[
                (
                    "balance".into(),
                    vec![(1.0, 0.1), (4.0, 0.03), (16.0, 0.008)],
                ),
                (
                    "optimal".into(),
                    vec![(1.0, 0.08), (4.0, f64::NAN), (16.0, 0.005)],
                ),
            ],
            true,
            true,
        );
        assert!(s.starts_with("<svg") && s.trim_end().ends_with("</svg>"));
        assert!(s.contains("relMSE &lt;vs&gt; spp"));
        assert_eq!(s.matches("<polyline").count(), 2);
        let b = bar_chart(
            "gain",
            "ratio",
            &["d=1".into(), "d=2".into()],
            &[("16 spp".into(), vec![1.5, 1.1])],
            Some(1.0),
        );
        assert_eq!(b.matches("<rect x=").count(), 2 + 1 + 1);
    }
}
