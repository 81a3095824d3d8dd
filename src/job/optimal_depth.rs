//! The automatic choice of D_opt, the largest depth weighted optimally: a pilot
//! render measures, per candidate D, the error of the estimate and what its systems cost, and
//! the job keeps optimal weights only up to the depth where they pay at equal time.
//!
//! Why a pilot and not the job's first pass: the choice fixes the layout of every task result
//! and tile checkpoint, so it must be known before the first task; and it must be a function of
//! the job alone (scene, settings, seed), so that in-process and distributed renders, tilings and
//! retries all make the same choice and keep the same bits. The pilot of a job of known spp is
//! deterministic (fixed seeds, its counters instead of clocks), and every pilot is small: `PILOT_REPLICAS` renders of `PILOT_SPP`
//! samples of at most `PILOT_PIXELS` pixels (about 37k pixel samples), and at most `PILOT_SHARE`
//! of the job (its cost is the job's, and at equal time a pilot larger than the gain it finds
//! makes optimal MIS lose to balance: Veach MIS at 64x64 and 128 spp took 1.118x balance's time
//! with the full pilot, 1.032x without, for 0.92-0.94x its error; BENCHMARKS.md, "Optimal against balance MIS"),
//! but never under `MIN_PILOT_PIXELS`.
//!
//! A job of known spp bounds the pilot by its pixel samples. A time budget bounds it by time,
//! which only a measurement turns into pixels: a probe (replica 0 at the smallest pilot frame,
//! and the cross-fitting solves of its pixels) is timed on the budget's clock, and the frame is
//! the largest whose replicas, the probe included, take `PILOT_SHARE` of the budget at the
//! probe's rate (the probe is replica 0 when that is the smallest frame). So a time-budgeted
//! job's choice depends on the speed of the machine that resolves it; it is made once, where
//! the job is resolved, and kept with it (the spp such a job reaches depends on that speed
//! anyway).
//!
//! The estimates: the pilot renders the whole frame at a reduced resolution (same camera, same
//! field of view; the techniques' relative densities per pixel do not depend on the resolution,
//! since light tracing's N_L grows with the pixel count) with optimal systems at every depth up to
//! `AUTO_MAX_DEPTH`, `PILOT_REPLICAS` times with independent seeds. From the same systems each
//! depth has its balance estimate (sum_i b_i / S) and its optimal one: the replica's samples
//! weighted with the optimal weights solved from the next replica's systems (`cross_fitted`;
//! weights solved from the samples they weight fit them, which at 4 spp made useless depths look
//! good), so each candidate D gives a pixel value per replica; the variance across replicas, over
//! (R^2 + eps) as in relMSE, is the candidate's error V(D) at `PILOT_SPP` samples.
//!
//! The cost: optimal MIS adds, per technique sample at depth d, the vector of its balance
//! weights (O(d) densities where balance needs O(1)) and one update of the depth's system
//! (`block_len(d)` multiply-adds, Kondapaneni et al. 2019, Algorithm 1 lines 6-7) where balance
//! adds one RGB value. Every sample adds W W^T with sum_i W_i = 1, so the entries of A sum to the
//! samples it took: the pilot counts those technique samples exactly. Relative to the render's
//! rays, time(D) / time(balance) = 1 + `COST_PER_TECHNIQUE_SAMPLE` x (technique samples at
//! depths <= D per pixel sample) / (rays per pixel sample), with the constant measured
//! (BENCHMARKS.md, "Optimal against balance MIS"). At equal time the
//! error is V(D) x time(D); D = 0 (balance) is a candidate, and a deeper D is kept only when it
//! beats the best shallower one by `MARGIN`.

use crate::integrator::RenderSettings;
use crate::mis::MisKind;
use crate::mis::optimal::OptimalAccum;
use crate::mis::progressive::Progressive;
use crate::scene::Scene;
use serde::{Deserialize, Serialize};

/// Deepest candidate D: the measured gains lie at depths 1-2 (BENCHMARKS.md, "Optimal against balance MIS"), and a depth-5
/// system already costs 49 values per technique sample.
pub const AUTO_MAX_DEPTH: u32 = 5;
/// Pixels of the pilot frame (at most; the job's frame when smaller).
pub const PILOT_PIXELS: u32 = 48 * 48;
/// The pilot's pixel samples are at most this share of a job of known spp...
pub const PILOT_SHARE: f64 = 1.0 / 64.0;
/// ...but its frame has at least this many pixels (or the job's, when smaller).
pub const MIN_PILOT_PIXELS: u32 = 16 * 16;
/// Independent pilot renders.
pub const PILOT_REPLICAS: u32 = 4;
/// Samples per pixel of each pilot render.
pub const PILOT_SPP: u32 = 4;
/// Cost of one technique sample at an optimal depth (its balance vector and its system
/// update), in rays traced. Fitted (BENCHMARKS.md, "Optimal against balance MIS") to instruction counts (callgrind) of
/// release renders at D_opt 0, 1 and 2 on ten scenes (0.17-0.19): the D_opt 1 overheads within
/// 1.2 points, D_opt 2 within 2.4 but for Veach's two scenes (overestimated by up to 3.6).
/// Instructions, not seconds: a count is exact where this machine's timings of a few per cent
/// are not.
pub const COST_PER_TECHNIQUE_SAMPLE: f64 = 0.18;
/// A deeper D must lower the predicted error at equal time by this fraction.
pub const MARGIN: f64 = 0.03;

/// What the pilot measured and chose; kept in the job's resolved settings, its status, the
/// render summary and the EXR header.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct DepthChoice {
    /// The chosen D_opt (0: balance at every depth).
    pub chosen: u32,
    /// The pilot frame, [width, height].
    pub pilot_resolution: [u32; 2],
    /// Independent pilot renders.
    pub replicas: u32,
    /// Samples per pixel of each pilot render.
    pub pilot_spp: u32,
    /// Per candidate D = 0 ..= the deepest tried: relMSE of one pilot render (its variance
    /// across the replicas over R^2 + eps).
    pub relmse: Vec<f64>,
    /// Per candidate D: standard error of `relmse` (over the pilot's pixels and channels).
    pub relmse_se: Vec<f64>,
    /// Per candidate D: predicted time relative to balance.
    pub time: Vec<f64>,
    /// Per candidate D: bytes of accumulators per pixel.
    pub bytes_per_pixel: Vec<usize>,
}

impl DepthChoice {
    /// Predicted relMSE x time of candidate D, relative to balance (1 for D = 0).
    pub fn relative_cost(&self, d: usize) -> f64 {
        let base = self.relmse[0] * self.time[0];
        if base > 0.0 {
            self.relmse[d] * self.time[d] / base
        } else {
            1.0
        }
    }

    /// One line for summaries and EXR headers.
    pub fn summary(&self) -> String {
        let per_d: Vec<String> = (0..self.relmse.len())
            .map(|d| format!("D{d} {:.3}", self.relative_cost(d)))
            .collect();
        format!(
            "auto D_opt {} (pilot {}x{}, {} x {} spp; relMSE x time vs balance: {})",
            self.chosen,
            self.pilot_resolution[0],
            self.pilot_resolution[1],
            self.replicas,
            self.pilot_spp,
            per_d.join(", ")
        )
    }
}

/// What bounds a pilot: the job's pixel samples where it has a count, its time budget where it
/// has one (both: whichever allows the smaller pilot); neither: the full `PILOT_PIXELS`.
#[derive(Clone, Copy, Default)]
pub struct JobSize<'a> {
    /// Pixel samples of the job.
    pub samples: Option<u64>,
    /// The job's time budget.
    pub budget: Option<Budget<'a>>,
}

/// A time budget: `seconds` on `clock` (seconds since any fixed start; wall or CPU time, as the
/// budget counts).
#[derive(Clone, Copy)]
pub struct Budget<'a> {
    /// The budget.
    pub seconds: f64,
    /// Seconds on the budget's clock.
    pub clock: &'a (dyn Fn() -> f64 + Sync),
}

/// Most pixels of the pilot frame for a job of `job_samples` pixel samples (None: no count, the
/// full frame): `PILOT_SHARE` of them, within `MIN_PILOT_PIXELS ..= PILOT_PIXELS`.
pub fn pilot_pixels(job_samples: Option<u64>) -> u32 {
    let Some(n) = job_samples else {
        return PILOT_PIXELS;
    };
    let per_pixel = (PILOT_REPLICAS * PILOT_SPP) as f64;
    let share = (n as f64 * PILOT_SHARE / per_pixel).floor();
    share.clamp(MIN_PILOT_PIXELS as f64, PILOT_PIXELS as f64) as u32
}

/// Most pixels of the pilot frame for a time budget of `budget_s` seconds, where a probe replica
/// of `probe_pixels` pixels took `probe_s`: the frame whose `PILOT_REPLICAS` replicas, at the
/// probe's rate per pixel, take `PILOT_SHARE` of the budget less the probe's own time (infinite
/// where the probe took no measurable time; below `MIN_PILOT_PIXELS` where the probe alone used
/// the share up: the caller clamps).
pub fn budget_pixels(budget_s: f64, probe_s: f64, probe_pixels: u32) -> f64 {
    let per_pixel = probe_s / probe_pixels.max(1) as f64;
    if !(per_pixel > 0.0 && per_pixel.is_finite()) {
        return f64::INFINITY;
    }
    (budget_s * PILOT_SHARE - probe_s) / (PILOT_REPLICAS as f64 * per_pixel)
}

/// The pilot frame of a `width` x `height` job: the same aspect, at most `max_pixels` pixels
/// (and at least one row and column: a frame narrower than the scaled one keeps its one pixel
/// and gives the other side fewer).
pub fn pilot_resolution(width: u32, height: u32, max_pixels: u32) -> [u32; 2] {
    let pixels = width as u64 * height as u64;
    if pixels <= max_pixels as u64 {
        return [width, height];
    }
    let scale = (max_pixels as f64 / pixels as f64).sqrt();
    let w = ((width as f64 * scale).floor() as u32).clamp(1, width);
    let h = ((height as f64 * scale).floor() as u32).clamp(1, height);
    let max = max_pixels.max(1);
    let w = w.min(max / h).max(1);
    let h = h.min(max / w).max(1);
    [w, h]
}

/// Seed of pilot replica `k` of a job seeded `seed` (none equals the job's own samples' seed).
fn replica_seed(seed: u64, k: u32) -> u64 {
    // SplitMix64 finaliser of (seed, k).
    let mut z = seed ^ (0x9e37_79b9_7f4a_7c15u64.wrapping_mul(k as u64 + 1)) ^ 0x5eed_9170;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// One pilot render: its systems, what lies outside them, and the update counts.
struct Replica {
    /// The optimal systems of depths 1 ..= dmax (None when the render kept none).
    systems: Option<OptimalAccum>,
    /// Per pixel: its sample count.
    counts: Vec<u32>,
    /// Per pixel: the estimate of everything outside the systems (depth 0 and beyond dmax).
    rest: Vec<[f64; 3]>,
    /// Light subpaths of the render (N_L).
    light_paths: u64,
    /// Technique samples per pixel sample added to depth d's systems, d = 1 ..= dmax (index
    /// d - 1).
    technique_samples: Vec<f64>,
    /// Rays per pixel sample.
    rays: f64,
}

/// Renders one pilot replica.
fn replica(scene: &Scene, s: &RenderSettings, dmax: u32) -> Replica {
    let job = super::Resolved::fixed(scene, s, 16, s.sample_block);
    let out = job.render_in_process(scene, &|_| {});
    let light_paths = out.film.light_paths();
    let acc = out.film.acc;
    let pixels = acc.tile.pixels();
    let rest = (0..pixels)
        .map(|i| {
            let n = acc.sums.count[i].max(1) as f64;
            let splat = acc.splat.get(i).copied().unwrap_or_default();
            std::array::from_fn(|c| (acc.sums.sum[i][c] + splat[c]) / n)
        })
        .collect();
    let mut technique_samples = vec![0.0; dmax as usize];
    if let Some(o) = acc.optimal.as_ref() {
        for i in 0..pixels {
            for d in 1..=dmax {
                technique_samples[d as usize - 1] += o.samples_taken(i, d);
            }
        }
    }
    let samples = out.stats.samples.max(1) as f64;
    for u in &mut technique_samples {
        *u /= samples;
    }
    Replica {
        systems: acc.optimal,
        counts: acc.sums.count,
        rest,
        light_paths,
        technique_samples,
        rays: out.stats.rays() as f64 / samples,
    }
}

/// The pixel values of every candidate D for replica `k`: depths <= D weighted with the optimal
/// weights solved from replica `j`'s systems, the others balance. With weights independent of
/// the samples they weight, the estimate is unbiased and its spread is what optimal weights
/// solved from other samples achieve (cross-fitting: Kondapaneni et al. 2019's progressive
/// estimator, one pass weighting the next). Weights solved from the samples they weight fit
/// those samples: at 4 spp that made depths that gain nothing look good (the glass caustic's
/// depth 3 at 0.585x balance's variance; 1.3x its error at equal time in the job).
/// Returns [pixel][D].
fn cross_fitted(k: &Replica, j: &Replica, dmax: u32, kappa: f64) -> Vec<[f64; 3]> {
    let nd = dmax as usize + 1;
    let pixels = k.rest.len();
    let mut values = vec![[0.0; 3]; pixels * nd];
    let (Some(ok), Some(oj)) = (&k.systems, &j.systems) else {
        for (i, r) in k.rest.iter().enumerate() {
            values[i * nd..(i + 1) * nd].fill(*r);
        }
        return values;
    };
    let mut weights = Progressive::new(dmax, pixels);
    weights.end_pass(oj, &j.counts, j.light_paths, kappa);
    for i in 0..pixels {
        weights.add_own(i, ok, i, k.counts[i]);
        for cand in 0..nd {
            let mut v = k.rest[i];
            for d in 1..=dmax {
                let f = if d as usize <= cand {
                    weights.estimate(ok, i, d, k.counts[i])
                } else {
                    ok.balance(i, d, k.counts[i])
                };
                for c in 0..3 {
                    v[c] += f[c];
                }
            }
            values[i * nd + cand] = v;
        }
    }
    values
}

/// Pilot replicas `ks` of `settings`' job, rendered at `w` x `h` (the scene's camera is given back;
/// None where the camera cannot take that resolution).
fn replicas_at(
    scene: &mut Scene,
    settings: &RenderSettings,
    dmax: u32,
    [w, h]: [u32; 2],
    ks: std::ops::Range<u32>,
) -> Option<Vec<Replica>> {
    let pilot_camera = scene.camera.with_resolution(w, h).ok()?;
    let camera = std::mem::replace(&mut scene.camera, pilot_camera);
    let rendered = ks
        .map(|k| {
            let s = RenderSettings {
                sample_block: PILOT_SPP,
                seed: replica_seed(settings.seed, k),
                mis: MisKind::Optimal,
                optimal_max_depth: dmax,
                depth_layers: false,
                strategies: false,
                ..settings.clone()
            };
            replica(scene, &s, dmax)
        })
        .collect();
    scene.camera = camera;
    Some(rendered)
}

/// Chooses D_opt for rendering `scene` (camera at the job's resolution) with `settings`, relMSE
/// measured with `eps`, for a job of `size`. Renders on the current rayon pool; the same inputs
/// give the same choice (a time budget aside: the module's doc).
pub fn choose(
    scene: &mut Scene,
    settings: &RenderSettings,
    eps: f64,
    size: JobSize,
) -> DepthChoice {
    let dmax = AUTO_MAX_DEPTH.min(settings.max_depth);
    let (width, height) = (scene.camera.width, scene.camera.height);
    let mut max_pixels = pilot_pixels(size.samples);
    // A time budget: the probe, replica 0 at the smallest frame, timed.
    let smallest = pilot_resolution(width, height, MIN_PILOT_PIXELS);
    let mut probe = None;
    if let Some(b) = size.budget
        && dmax > 0
        && pilot_resolution(width, height, max_pixels) != smallest
    {
        let t0 = (b.clock)();
        probe = replicas_at(scene, settings, dmax, smallest, 0..1);
        // Timed with the analysis a replica's pixels will cost (its solves; the weights solved
        // from the probe itself are thrown away).
        if let Some(p) = probe.as_ref().and_then(|p| p.first()) {
            std::hint::black_box(cross_fitted(p, p, dmax, settings.optimal_kappa));
        }
        let spent = (b.clock)() - t0;
        let allowed = budget_pixels(b.seconds, spent, smallest[0] * smallest[1]);
        max_pixels = allowed.clamp(MIN_PILOT_PIXELS as f64, max_pixels as f64) as u32;
    }
    let [w, h] = pilot_resolution(width, height, max_pixels);
    let mut choice = DepthChoice {
        chosen: 0,
        pilot_resolution: [w, h],
        replicas: PILOT_REPLICAS,
        pilot_spp: PILOT_SPP,
        relmse: vec![0.0],
        relmse_se: vec![0.0],
        time: vec![1.0],
        bytes_per_pixel: vec![0],
    };
    if dmax == 0 {
        return choice;
    }
    let rendered = match probe {
        // The probe is replica 0 where the budget allows no larger frame.
        Some(mut first) if [w, h] == smallest => {
            let Some(rest) = replicas_at(scene, settings, dmax, [w, h], 1..PILOT_REPLICAS) else {
                return choice;
            };
            first.extend(rest);
            first
        }
        _ => match replicas_at(scene, settings, dmax, [w, h], 0..PILOT_REPLICAS) {
            Some(r) => r,
            None => return choice,
        },
    };
    // Replica k weighted with the weights of replica k + 1 (mod the count).
    let n = rendered.len();
    let values: Vec<Vec<[f64; 3]>> = (0..n)
        .map(|k| {
            let next = &rendered[(k + 1) % n];
            cross_fitted(&rendered[k], next, dmax, settings.optimal_kappa)
        })
        .collect();

    let nd = dmax as usize + 1;
    let pixels = (w * h) as usize;
    let k = PILOT_REPLICAS as f64;
    let mut relmse = vec![0.0; nd];
    let mut relmse_sq = vec![0.0; nd];
    for i in 0..pixels {
        for c in 0..3 {
            // The pixel's value: the mean of the balance estimates.
            let r = values.iter().map(|p| p[i * nd][c]).sum::<f64>() / k;
            let norm = r * r + eps;
            for (cand, e) in relmse.iter_mut().enumerate() {
                let vals = values.iter().map(|p| p[i * nd + cand][c]);
                let mean = vals.clone().sum::<f64>() / k;
                let var = vals.map(|v| (v - mean) * (v - mean)).sum::<f64>() / (k - 1.0);
                *e += var / norm;
                relmse_sq[cand] += (var / norm) * (var / norm);
            }
        }
    }
    let count = (pixels * 3) as f64;
    let rays = rendered.iter().map(|p| p.rays).sum::<f64>() / k;
    let mut time = vec![1.0; nd];
    let mut bytes = vec![0; nd];
    for cand in 1..nd {
        let technique_samples: f64 = (0..cand)
            .map(|d| rendered.iter().map(|p| p.technique_samples[d]).sum::<f64>() / k)
            .sum();
        time[cand] = 1.0 + COST_PER_TECHNIQUE_SAMPLE * technique_samples / rays.max(1.0);
        bytes[cand] = crate::mis::Layout::new(cand as u32).bytes_per_pixel();
    }
    choice.relmse = relmse.iter().map(|e| e / count).collect();
    choice.relmse_se = (0..nd)
        .map(|c| {
            let m = relmse[c] / count;
            ((relmse_sq[c] / count - m * m).max(0.0) / (count - 1.0).max(1.0)).sqrt()
        })
        .collect();
    choice.time = time;
    choice.bytes_per_pixel = bytes;
    let mut best = 0;
    for cand in 1..nd {
        if choice.relative_cost(cand) < choice.relative_cost(best) * (1.0 - MARGIN) {
            best = cand;
        }
    }
    choice.chosen = best as u32;
    choice
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pilot is at most `PILOT_SHARE` of a job of known size, within its bounds, and full
    /// for a time budget; its frame keeps the job's aspect within that many pixels.
    #[test]
    fn the_pilot_is_a_bounded_share_of_the_job() {
        let per_pixel = (PILOT_REPLICAS * PILOT_SPP) as f64;
        assert_eq!(pilot_pixels(None), PILOT_PIXELS);
        assert_eq!(pilot_pixels(Some(1920 * 1080 * 64)), PILOT_PIXELS);
        // 64x64 at 128 spp: 512 pixels of 16 samples, 1/64 of the job.
        assert_eq!(pilot_pixels(Some(64 * 64 * 128)), 512);
        assert_eq!(pilot_pixels(Some(1000)), MIN_PILOT_PIXELS);
        assert_eq!(pilot_pixels(Some(0)), MIN_PILOT_PIXELS);
        assert_eq!(pilot_pixels(Some(u64::MAX)), PILOT_PIXELS);
        // Between the bounds, the share and no less than a pixel short of it.
        for job in (1..40).map(|k| 3u64.pow(k / 2) << (k % 2)) {
            let px = pilot_pixels(Some(job)) as f64;
            let share = job as f64 * PILOT_SHARE / per_pixel;
            if px > MIN_PILOT_PIXELS as f64 && px < PILOT_PIXELS as f64 {
                assert!(px <= share && px > share - 1.0, "job {job}: {px} pixels");
            }
        }
        // The frame: at most that many pixels (or the whole frame), at least one row and column,
        // and the job's aspect where the frame is not a line.
        for (w, h, max) in [
            (64, 64, 512),
            (1920, 1080, 2304),
            (24, 20, 256),
            (10, 10, 256),
            (4000, 1, 256),
            (1, 16384, 2304),
            (16384, 2, 256),
            (3, 100_000, 1),
        ] {
            let [pw, ph] = pilot_resolution(w, h, max);
            assert!(
                pw >= 1 && ph >= 1 && pw <= w && ph <= h,
                "{w}x{h}: {pw}x{ph}"
            );
            assert!(
                pw * ph <= max || (pw, ph) == (w, h),
                "{w}x{h} in {max}: {pw}x{ph}"
            );
            let aspect = |a: u32, b: u32| a as f64 / b as f64;
            assert!(
                w.min(h) < 10 || (aspect(pw, ph) / aspect(w, h) - 1.0).abs() < 0.1,
                "{w}x{h}: {pw}x{ph}"
            );
        }
        assert_eq!(pilot_resolution(64, 64, 512), [22, 22]);
        assert_eq!(pilot_resolution(10, 10, 256), [10, 10]);
    }

    /// A time budget's pilot: the probe and the replicas at the probe's rate take the share of
    /// the budget.
    #[test]
    fn a_budgets_pilot_takes_its_share_at_the_probes_rate() {
        for (budget, probe, px) in [(3.0, 0.004, 256), (60.0, 0.01, 240), (1.0, 0.001, 256)] {
            let p = budget_pixels(budget, probe, px);
            let per_pixel = probe / px as f64;
            let total = probe + PILOT_REPLICAS as f64 * p * per_pixel;
            assert!((total / (budget * PILOT_SHARE) - 1.0).abs() < 1e-9, "{p}");
        }
        // The probe alone past the share: below any frame (the caller takes the smallest).
        assert!(budget_pixels(0.1, 0.01, 256) < 0.0);
        // A probe too fast for the clock: no bound from time.
        assert_eq!(budget_pixels(3.0, 0.0, 256), f64::INFINITY);
    }
}
