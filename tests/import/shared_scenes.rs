//! The public scenes in `../shared/scenes`: loaded, rendered, compared with our own scenes and
//! between formats.

use crate::common;
use crate::common::import::{assert_has, close, load, warning};
use omis::film::PixelSums;
use omis::geometry::{Vec2, Vec3};
use omis::integrator::RenderSettings;
use omis::sampler::SamplerKind;
use omis::scene::Scene;
use std::path::Path;
use std::time::Instant;

fn render(scene: &Scene, spp: u32, max_depth: u32, seed: u64) -> PixelSums {
    let settings = RenderSettings {
        sample_block: spp,
        max_depth,
        seed,
        sampler: SamplerKind::Independent,
        ..Default::default()
    };
    omis::job::Resolved::fixed(scene, &settings, 16, 64)
        .render_in_process(scene, &|_| {})
        .sums()
        .clone()
}

/// Compares two renders region by region, every channel, within 4 combined standard errors.
/// Returns the number of regions with signal.
fn compare_regions(
    what: &str,
    a: &PixelSums,
    b: &PixelSums,
    regions: &[(usize, usize, usize, usize)],
) -> usize {
    let mut lit = 0;
    let mut worst: f64 = 0.0;
    for &(x0, y0, x1, y1) in regions {
        for c in 0..3 {
            let (ma, sa) = common::sums_region(a, x0, y0, x1, y1, c);
            let (mb, sb) = common::sums_region(b, x0, y0, x1, y1, c);
            let se = (sa * sa + sb * sb).sqrt();
            // A tiny relative allowance covers f32 rounding where both are exact.
            let tol = 4.0 * se + 1e-6 * ma.abs().max(mb.abs());
            assert!(
                (ma - mb).abs() <= tol,
                "{what}: region ({x0},{y0})-({x1},{y1}) channel {c}: {ma} vs {mb} (tol {tol})"
            );
            worst = worst.max((ma - mb).abs() / se.max(1e-12));
            if ma > 1e-3 {
                lit += 1;
            }
        }
    }
    eprintln!(
        "{what}: worst difference {worst:.2} standard errors over {} regions",
        regions.len()
    );
    lit
}

fn grid(w: usize, h: usize, n: usize) -> Vec<(usize, usize, usize, usize)> {
    let mut r = Vec::new();
    for ry in 0..n {
        for rx in 0..n {
            r.push((rx * w / n, ry * h / n, (rx + 1) * w / n, (ry + 1) * h / n));
        }
    }
    r
}

fn mean_rgb(sums: &PixelSums) -> [f64; 3] {
    sums.mean().mean()
}

/// Peak resident memory of this process (VmHWM), in MiB.
fn peak_memory_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

#[test]
fn shared_scenes_load_and_render() {
    let Some(dir) = common::shared_scenes("shared_scenes_load_and_render") else {
        return;
    };
    for (rel, w, h) in [
        ("cornell-box/pbrt-v3/scene.pbrt", 24, 24),
        ("veach-mis/pbrt-v3/scene.pbrt", 32, 18),
        ("veach-mis/mitsuba/scene.xml", 32, 18),
        ("veach-bidir/pbrt-v3/scene.pbrt", 24, 24),
        ("staircase/mitsuba/scene.xml", 18, 32),
    ] {
        let t0 = Instant::now();
        let mut s = load(&dir.join(rel));
        let load_s = t0.elapsed().as_secs_f64();
        eprintln!(
            "{rel}: {} triangles, {} spheres, {} lights, {} materials, loaded in {load_s:.2} s (BVH {:.2} s)",
            s.stats.triangles,
            s.spheres.len(),
            s.lights.len(),
            s.materials.len(),
            s.stats.bvh_build_seconds
        );
        for w in &s.warnings {
            eprintln!("  warning: {w}");
        }
        assert!(s.stats.lights > 0);
        s.camera = s.camera.with_resolution(w, h).expect("resolution");
        let t0 = Instant::now();
        let sums = render(&s, 4, 3, 1);
        let m = mean_rgb(&sums);
        eprintln!(
            "  rendered {w}x{h} at 4 spp in {:.2} s: mean {m:?}",
            t0.elapsed().as_secs_f64()
        );
        assert!(
            m.iter().all(|c| c.is_finite() && *c > 0.0),
            "{rel}: mean {m:?}"
        );
    }
}

#[test]
fn cornell_box_pbrt_matches_our_json_scene() {
    let Some(dir) = common::shared_scenes("cornell_box_pbrt_matches_our_json_scene") else {
        return;
    };
    let mut pbrt = load(&dir.join("cornell-box/pbrt-v3/scene.pbrt"));
    let mut json = load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.json"));
    // Same camera: Bitterli's world-to-camera matrix is a reflection, so no mirroring.
    assert!(!pbrt.camera.flip_x());
    assert!((pbrt.camera.position - json.camera.position).length() < 1e-5);
    assert!((pbrt.camera.forward() - json.camera.forward()).length() < 1e-5);
    assert!(close(pbrt.camera.vfov_deg, json.camera.vfov_deg, 1e-6));
    assert_eq!(pbrt.defaults.max_depth, Some(5));
    assert_eq!(pbrt.defaults.spp, Some(64));
    assert_has(warning(&pbrt, "PixelFilter"), &["\"triangle\""]);
    pbrt.camera = pbrt.camera.with_resolution(64, 64).expect("resolution");
    json.camera = json.camera.with_resolution(64, 64).expect("resolution");
    let a = render(&pbrt, 96, 5, 1);
    let b = render(&json, 96, 5, 2);
    let lit = compare_regions("cornell pbrt vs json", &a, &b, &grid(64, 64, 4));
    assert!(
        lit >= 40,
        "the image is mostly dark ({lit} lit region-channels)"
    );
    // The red wall is on the left, the green on the right (as in Tungsten's reference).
    let (red_left, _) = common::sums_region(&a, 2, 24, 8, 40, 0);
    let (green_left, _) = common::sums_region(&a, 2, 24, 8, 40, 1);
    let (red_right, _) = common::sums_region(&a, 56, 24, 62, 40, 0);
    let (green_right, _) = common::sums_region(&a, 56, 24, 62, 40, 1);
    assert!(red_left > 2.0 * green_left && green_right > 2.0 * red_right);
}

#[test]
fn veach_mis_pbrt_matches_mitsuba_where_the_models_agree() {
    let Some(dir) = common::shared_scenes("veach_mis_pbrt_matches_mitsuba_where_the_models_agree")
    else {
        return;
    };
    let mut pbrt = load(&dir.join("veach-mis/pbrt-v3/scene.pbrt"));
    let mut mts = load(&dir.join("veach-mis/mitsuba/scene.xml"));
    for w in &mts.warnings {
        eprintln!("mitsuba warning: {w}");
    }
    // Same camera: pbrt's 20.11 degrees on the short (vertical) axis is Mitsuba's 35 on x.
    assert!((pbrt.camera.position - mts.camera.position).length() < 1e-4);
    assert!((pbrt.camera.forward() - mts.camera.forward()).length() < 1e-5);
    assert!(!pbrt.camera.flip_x() && !mts.camera.flip_x());
    let (w, h) = (64usize, 36usize);
    pbrt.camera = pbrt
        .camera
        .with_resolution(w as u32, h as u32)
        .expect("resolution");
    mts.camera = mts
        .camera
        .with_resolution(w as u32, h as u32)
        .expect("resolution");
    assert!(
        close(pbrt.camera.vfov_deg, mts.camera.vfov_deg, 1e-4),
        "{} vs {}",
        pbrt.camera.vfov_deg,
        mts.camera.vfov_deg
    );
    // Direct lighting (max depth 1): the diffuse floor and back wall see the three sphere lights
    // through the same geometry in both files (the plates only cast shadows). The plates
    // themselves differ: pbrt-v3's `metal` is GGX with the full Fresnel reflectance, Mitsuba's
    // (Tungsten's) roughconductor is Beckmann (here approximated by GGX of the same alpha) with
    // specularReflectance 0.3, so plate pixels are ~0.3x as bright. At depth >= 2 the floor
    // also receives light reflected by the plates and would differ too.
    let a = render(&pbrt, 64, 1, 1);
    let b = render(&mts, 64, 1, 2);
    // Regions away from the plates (picked from a 320x180 render, in 64x36 pixels): the back
    // wall above them (with the lights), the wall and floor left and right of them, and the
    // floor below the lowest plate.
    let mut regions = Vec::new();
    for rx in 0..8 {
        let (x0, x1) = (rx * w / 8, (rx + 1) * w / 8);
        regions.push((x0, 0, x1, 8));
        regions.push((x0, 34, x1, 36));
    }
    for ry in 0..3 {
        let (y0, y1) = (8 + ry * 26 / 3, 8 + (ry + 1) * 26 / 3);
        regions.push((0, y0, 6, y1));
        regions.push((58, y0, 64, y1));
    }
    let lit = compare_regions("veach-mis pbrt vs mitsuba (diffuse)", &a, &b, &regions);
    assert!(lit >= 50, "too few lit regions ({lit})");
    // And the plates do differ: Mitsuba's are darker (specularReflectance 0.3).
    let plates = |s: &PixelSums| common::sums_region(s, 0, 12, w, 24, 1).0;
    eprintln!("plate band: pbrt {} mitsuba {}", plates(&a), plates(&b));
    assert!(plates(&b) < plates(&a));
}

/// Averages `b` x `b` blocks: what is left of the difference between two images is bias, not
/// noise.
fn blocks(img: &omis::film::Image, b: usize) -> omis::film::Image {
    let (w, h) = (img.width / b, img.height / b);
    let mut out = omis::film::Image::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let mut s = Vec3::ZERO;
            for dy in 0..b {
                for dx in 0..b {
                    s += img.get(x * b + dx, y * b + dy);
                }
            }
            out.set(x, y, s / (b * b) as f32);
        }
    }
    out
}

/// Nearest-neighbour upscaling of an RGB8 buffer, for viewing block maps.
fn upscale(data: &[u8], w: usize, h: usize, f: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() * f * f);
    for y in 0..h * f {
        for x in 0..w * f {
            let i = 3 * ((y / f) * w + x / f);
            out.extend_from_slice(&data[i..i + 3]);
        }
    }
    out
}

/// Path-traced staircase against Tungsten's converged reference, at the reference resolution.
/// Run with `cargo test --release --test import -- --ignored staircase --nocapture`
/// (OMIS_STAIRCASE_SPP sets the samples per pixel, default 64). Prints load time, BVH build
/// time, peak memory (VmHWM), pixel samples per second and relMSE, and writes the render, the
/// reference and error maps to the temporary folder.
#[test]
#[ignore]
fn staircase_relmse_against_tungsten() {
    let Some(dir) = common::shared_scenes("staircase_relmse_against_tungsten") else {
        return;
    };
    let scene_path = dir.join("staircase/mitsuba/scene.xml");
    let t0 = Instant::now();
    let scene = load(&scene_path);
    let load_s = t0.elapsed().as_secs_f64();
    let peak_after_load = peak_memory_mib().unwrap_or(f64::NAN);
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    eprintln!(
        "staircase: {} triangles, {} materials; load {load_s:.2} s (BVH build {:.3} s of it); peak memory (VmHWM) after load {peak_after_load:.0} MiB",
        scene.stats.triangles,
        scene.materials.len(),
        scene.stats.bvh_build_seconds,
    );
    let reference =
        omis::film::image::exr_io::read_exr(&dir.join("staircase/mitsuba/TungstenRender.exr"))
            .expect("reference EXR");
    assert_eq!(
        (scene.camera.width as usize, scene.camera.height as usize),
        (reference.width, reference.height),
        "the scene's film is the reference's resolution"
    );
    let spp: u32 = std::env::var("OMIS_STAIRCASE_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(64);
    let max_depth = scene.defaults.max_depth.unwrap_or(64);
    let settings = RenderSettings {
        sample_block: spp,
        max_depth,
        seed: 1,
        sampler: SamplerKind::Sobol,
        ..Default::default()
    };
    let out =
        omis::job::Resolved::fixed(&scene, &settings, 16, 64).render_in_process(&scene, &|_| {});
    let img = out.image();
    let rate = out.stats.samples as f64 / out.seconds;
    let stats = omis::film::image::metrics::compare(&img, &reference, 0.01).expect("same size");
    // 8x8 block means: the noise of the render mostly averages out, model differences stay.
    let (bi, br) = (blocks(&img, 8), blocks(&reference, 8));
    let bias = omis::film::image::metrics::compare(&bi, &br, 0.01).expect("same size");
    eprintln!(
        "staircase {}x{} at {spp} spp, max depth {max_depth}: relMSE {:.5} (eps 0.01), MSE {:.5}; relMSE of 8x8 block means {:.5}; {:.1} s, {:.0} pixel samples/s ({} threads); peak memory (VmHWM) {:.0} MiB",
        img.width,
        img.height,
        stats.relmse,
        stats.mse,
        bias.relmse,
        out.seconds,
        rate,
        rayon::current_num_threads(),
        peak_memory_mib().unwrap_or(f64::NAN)
    );
    let mr = img.mean();
    let rr = reference.mean();
    eprintln!("mean RGB: ours {mr:?}, Tungsten {rr:?}");
    // Attribute the differences to materials: the material seen through each pixel's centre.
    let mut per: std::collections::BTreeMap<String, (usize, f64, f64, f64)> = Default::default();
    for y in 0..img.height {
        for x in 0..img.width {
            let ray = scene.camera.ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let name = match scene.intersect(&ray) {
                Some(h) => scene.materials[h.material as usize].name.clone(),
                None => "(nothing)".into(),
            };
            let (a, r) = (img.get(x, y), reference.get(x, y));
            let e = per.entry(name).or_default();
            e.0 += 1;
            e.1 += omis::geometry::luminance(a) as f64;
            e.2 += omis::geometry::luminance(r) as f64;
            for c in 0..3 {
                let d = (a[c] - r[c]) as f64;
                e.3 += d * d / ((r[c] as f64).powi(2) + 0.01);
            }
        }
    }
    let mut rows: Vec<_> = per.into_iter().collect();
    rows.sort_by_key(|r| std::cmp::Reverse(r.1.0));
    let total = (3 * img.width * img.height) as f64;
    eprintln!("material            pixels   ours/Tungsten (luminance)   share of relMSE");
    for (name, (n, a, r, e)) in rows {
        eprintln!(
            "{name:<20}{n:>7}   {:>8.4}                    {:>6.4}",
            a / r.max(1e-12),
            e / total
        );
    }
    let tmp = std::env::temp_dir();
    let paths = [
        "omis-staircase.png",
        "omis-staircase-tungsten.png",
        "omis-staircase-error-map.png",
        "omis-staircase-error-map-8x8.png",
    ]
    .map(|n| tmp.join(n));
    omis::film::image::png::write_png(&paths[0], &img, 1.0).expect("write render");
    omis::film::image::png::write_png(&paths[1], &reference, 1.0).expect("write reference");
    let map = omis::film::image::error_map::relative_error_map(&img, &reference, 0.01, 1.0)
        .expect("error map");
    omis::film::image::png::write_rgb8(&paths[2], img.width, img.height, &map).expect("write map");
    // Block map at a finer scale (saturating at 25 %), shown at full size.
    let bmap =
        omis::film::image::error_map::relative_error_map(&bi, &br, 0.01, 0.25).expect("error map");
    let up = upscale(&bmap, bi.width, bi.height, 8);
    omis::film::image::png::write_rgb8(&paths[3], bi.width * 8, bi.height * 8, &up)
        .expect("write map");
    eprintln!(
        "render: {}\nreference (same tone mapping): {}\nerror map (red: brighter than Tungsten, green: darker; saturates at 100 %): {}\nerror map of 8x8 block means (saturates at 25 %): {}",
        paths[0].display(),
        paths[1].display(),
        paths[2].display(),
        paths[3].display()
    );
    assert!(stats.relmse.is_finite());
}
