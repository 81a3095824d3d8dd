//! The `omis` binary's command-line contract: render and diff, their JSON summaries, EXRs that
//! OpenEXR's own tools read, and one-line errors with a non-zero exit.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn omis(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_omis"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run omis")
}

fn folder(name: &str) -> PathBuf {
    common::folder("cli", name)
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn last_json(out: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().expect("some stdout");
    serde_json::from_str(line).unwrap_or_else(|e| panic!("last line is not JSON ({e}): {line}"))
}

/// Runs `common` through the service (2 workers, to `svc`) and in-process (to `inp`); both must
/// succeed.
fn both_modes(common: &[&str], svc: &Path, inp: &Path) -> (Output, Output) {
    let a = omis(&[common, &["--workers", "2", "--out", s(svc)]].concat());
    assert!(
        a.status.success(),
        "{common:?} via the service: {}",
        String::from_utf8_lossy(&a.stderr)
    );
    let b = omis(&[common, &["--in-process", "--out", s(inp)]].concat());
    assert!(
        b.status.success(),
        "{common:?} in-process: {}",
        String::from_utf8_lossy(&b.stderr)
    );
    (a, b)
}

fn assert_one_line_error(out: &Output, needle: &str) {
    assert!(!out.status.success(), "expected failure");
    let err = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one line of error, got: {err}");
    assert!(
        lines[0].contains(needle),
        "error '{}' should mention '{needle}'",
        lines[0]
    );
}

#[test]
fn render_writes_exr_png_and_a_json_summary() {
    let d = folder("render");
    let exr = d.join("cb.exr");
    let png = d.join("cb.png");
    let out = omis(&[
        "render",
        "scenes/cornell-box.json",
        "--spp",
        "2",
        "--resolution",
        "32x24",
        "--out",
        s(&exr),
        "--png",
        s(&png),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j = last_json(&out);
    assert_eq!(j["spp"], 2);
    assert_eq!(j["width"], 32);
    assert_eq!(j["height"], 24);
    assert!(j["seconds"].as_f64().expect("seconds") > 0.0);
    assert!(j["pixel_samples_per_second"].as_f64().expect("rate") > 0.0);
    let mean = j["mean_rgb"].as_array().expect("mean_rgb");
    assert_eq!(mean.len(), 3);
    assert!(mean.iter().all(|v| v.as_f64().expect("number") > 0.0));
    assert!(j.get("relmse").is_none());
    let img = omis::film::image::exr_io::read_exr(&exr).expect("EXR reads");
    assert_eq!((img.width, img.height), (32, 24));
    assert!(std::fs::metadata(&png).expect("png").len() > 0);

    // The image against itself: relMSE 0, in render and in diff.
    let out = omis(&[
        "render",
        "scenes/cornell-box.json",
        "--spp",
        "2",
        "--resolution",
        "32x24",
        "--out",
        s(&d.join("again.exr")),
        "--reference",
        s(&exr),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(last_json(&out)["relmse"], 0.0);
    let map = d.join("err.png");
    let out = omis(&[
        "diff",
        s(&exr),
        s(&d.join("again.exr")),
        "--error-map",
        s(&map),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(last_json(&out)["relmse"], 0.0);
    assert!(map.exists());
}

/// EXRs written through the service (their blocks compressed by the last pass's merge tasks):
/// ZIP blocks of 16 lines with the default tiles, of one line with 8-pixel tiles. OpenEXR's own
/// tools read both, every pixel.
#[test]
fn exr_opens_in_openexr_tools() {
    let d = folder("openexr");
    let tool = Command::new("exrmaketiled").arg("-h").output();
    if tool.is_err() {
        assert!(
            std::env::var_os("OMIS_REQUIRE_OPENEXR").is_none(),
            "OpenEXR tools are required (OMIS_REQUIRE_OPENEXR) but exrmaketiled is missing"
        );
        eprintln!("skipped: OpenEXR's tools (Debian package openexr) are not installed");
        return;
    }
    for (tile, compression) in [
        ("32", "zip, multi-scanline blocks"),
        ("8", "zip, individual scanlines"),
    ] {
        let exr = d.join(format!("f{tile}.exr"));
        let out = omis(&[
            "render",
            "scenes/furnace.json",
            "--spp",
            "4",
            "--resolution",
            "20x40",
            "--tile-size",
            tile,
            "--out",
            s(&exr),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let header = Command::new("exrheader")
            .arg(&exr)
            .output()
            .expect("exrheader");
        assert!(
            header.status.success(),
            "{}",
            String::from_utf8_lossy(&header.stderr)
        );
        let text = String::from_utf8_lossy(&header.stdout);
        assert!(
            text.contains("variance.R") && text.contains("omis.spp") && text.contains(compression),
            "{text}"
        );
        // OpenEXR reads every pixel and rewrites them tiled; we read its file back: same image.
        let tiled = d.join(format!("tiled{tile}.exr"));
        let t = Command::new("exrmaketiled")
            .arg(&exr)
            .arg(&tiled)
            .output()
            .expect("exrmaketiled");
        assert!(t.status.success(), "{}", String::from_utf8_lossy(&t.stderr));
        let a = omis::film::image::exr_io::read_exr_layers(&exr).expect("ours");
        let b = omis::film::image::exr_io::read_exr_layers(&tiled).expect("OpenEXR's");
        assert_eq!(a, b);
    }
}

#[test]
fn bad_input_exits_nonzero_with_one_line() {
    let d = folder("bad");
    assert_one_line_error(
        &omis(&["render", "no/such/scene.json"]),
        "no/such/scene.json",
    );
    assert_one_line_error(
        &omis(&["render", "scenes/furnace.json", "--resolution", "0x5"]),
        "resolution",
    );
    assert_one_line_error(
        &omis(&["render", "scenes/furnace.json", "--spp", "0"]),
        "spp",
    );
    assert_one_line_error(
        &omis(&[
            "render",
            "scenes/furnace.json",
            "--roulette",
            "--no-roulette",
        ]),
        "--no-roulette",
    );
    assert_one_line_error(
        &omis(&["render", "scenes/furnace.json", "--roulette-from", "0"]),
        "--roulette-from",
    );
    assert_one_line_error(
        &omis(&[
            "render",
            "scenes/furnace.json",
            "--roulette-from",
            "2",
            "--no-roulette",
        ]),
        "--no-roulette",
    );
    assert_one_line_error(
        &omis(&["render", "scenes/furnace.json", "--spp", "abc"]),
        "--spp",
    );
    assert_one_line_error(&omis(&["render", "--bogus"]), "--bogus");
    assert_one_line_error(&omis(&["render"]), "<SCENE>");
    let bad_scene = d.join("bad.json");
    std::fs::write(&bad_scene, "{\"camera\": 3}").expect("write");
    assert_one_line_error(&omis(&["render", s(&bad_scene)]), "camera");
    let not_exr = d.join("x.exr");
    std::fs::write(&not_exr, "not an exr").expect("write");
    assert_one_line_error(
        &omis(&["render", "scenes/furnace.json", "--reference", s(&not_exr)]),
        "x.exr",
    );
    assert_one_line_error(&omis(&["diff", s(&not_exr), s(&not_exr)]), "x.exr");
    // A reference of the wrong size is refused before rendering.
    let small = d.join("small.exr");
    let out = omis(&[
        "render",
        "scenes/furnace.json",
        "--spp",
        "1",
        "--resolution",
        "4x4",
        "--out",
        s(&small),
    ]);
    assert!(out.status.success());
    assert_one_line_error(
        &omis(&[
            "render",
            "scenes/furnace.json",
            "--spp",
            "1",
            "--reference",
            s(&small),
        ]),
        "4x4",
    );
    // An output that can never be written is refused before rendering, in both modes: with
    // 4096 spp at 1024x1024 a render that started first would run for minutes.
    for mode in [&[][..], &["--in-process"][..]] {
        let started = std::time::Instant::now();
        let mut args = vec![
            "render",
            "scenes/furnace.json",
            "--spp",
            "4096",
            "--resolution",
            "1024x1024",
            "--out",
            "no/such/folder/out.exr",
        ];
        args.extend_from_slice(mode);
        assert_one_line_error(&omis(&args), "no/such/folder");
        assert!(
            started.elapsed().as_secs() < 20,
            "refused only after rendering"
        );
    }
}

#[test]
fn render_through_the_service_equals_the_in_process_render() {
    let d = folder("modes");
    let svc = d.join("svc.exr");
    let inp = d.join("inp.exr");
    let common = [
        "render",
        "scenes/cornell-box.json",
        "--spp",
        "12",
        "--pass-size",
        "4",
        "--tile-size",
        "8",
        "--resolution",
        "24x20",
        "--integrator",
        "bdpt",
        "--mis",
        "optimal",
        "--optimal-max-depth",
        "5",
        "--depth-layers",
        "--json",
    ];
    let (a, b) = both_modes(&common, &svc, &inp);
    assert_eq!(last_json(&a)["mode"], "2 worker processes");
    assert_eq!(last_json(&b)["mode"], "in-process");
    assert!(
        last_json(&a)["accumulator_bytes_per_pixel"]
            .as_u64()
            .unwrap_or(0)
            > 1000
    );
    let la = omis::film::image::exr_io::read_exr_layers(&svc).expect("service EXR");
    let lb = omis::film::image::exr_io::read_exr_layers(&inp).expect("in-process EXR");
    let names: Vec<&str> = la.iter().map(|(n, _)| n.as_str()).collect();
    assert!(
        names.contains(&"depth1") && names.contains(&""),
        "{names:?}"
    );
    // Every layer, bit for bit: the same tasks merged in the same order.
    assert_eq!(la, lb);
}

#[test]
fn auto_optimal_depth_is_chosen_once_the_same_way_in_both_modes_and_reported() {
    // Optimal MIS without --optimal-max-depth: the coordinator's pilot and the in-process
    // pilot make the same choice, the images are equal bit for bit, and the summary, the job
    // status and the EXR header say what was chosen.
    let d = folder("auto-dopt");
    let svc = d.join("svc.exr");
    let inp = d.join("inp.exr");
    let common = [
        "render",
        "scenes/cornell-box-small-light.json",
        "--spp",
        "8",
        "--pass-size",
        "4",
        "--tile-size",
        "8",
        "--resolution",
        "24x20",
        "--integrator",
        "bdpt",
        "--mis",
        "optimal",
        "--json",
    ];
    let (a, b) = both_modes(&common, &svc, &inp);
    let (ja, jb) = (last_json(&a), last_json(&b));
    let choice = &jb["optimal_depth"];
    assert!(choice["chosen"].is_u64(), "{jb}");
    // 24x20 at 8 spp is 3840 pixel samples: the pilot takes its smallest frame (256 pixels at
    // most, the job's aspect), not the full 48x48 of a large job.
    assert_eq!(
        choice["pilot_resolution"],
        serde_json::json!([17, 14]),
        "{jb}"
    );
    assert_eq!(
        choice["relmse"].as_array().map(|v| v.len()),
        Some(6),
        "{jb}"
    );
    assert_eq!(ja["optimal_depth"], *choice);
    assert_eq!(ja["optimal_max_depth"], choice["chosen"]);
    assert_eq!(jb["optimal_max_depth"], choice["chosen"]);
    assert!(
        String::from_utf8_lossy(&b.stderr).contains("optimal MIS: auto D_opt"),
        "{}",
        String::from_utf8_lossy(&b.stderr)
    );
    assert_eq!(
        omis::film::image::exr_io::read_exr_layers(&svc).expect("service EXR"),
        omis::film::image::exr_io::read_exr_layers(&inp).expect("in-process EXR")
    );
    for f in [&svc, &inp] {
        let meta = exr::meta::MetaData::read_from_file(f, false).expect("EXR header");
        let other = &meta.headers[0].own_attributes.other;
        let text = |k: &str| match other.get(&exr::meta::attribute::Text::from(k)) {
            Some(exr::meta::attribute::AttributeValue::Text(t)) => t.to_string(),
            v => panic!("{k}: {v:?}"),
        };
        assert_eq!(
            text("omis.optimal_max_depth"),
            choice["chosen"].to_string(),
            "{}",
            f.display()
        );
        assert!(text("omis.optimal_max_depth_auto").starts_with("auto D_opt"));
    }
    // An explicit depth runs no pilot.
    let c = omis(
        &[
            &common[..],
            &["--in-process", "--optimal-max-depth", "2", "--out", s(&inp)],
        ]
        .concat(),
    );
    assert!(c.status.success(), "{}", String::from_utf8_lossy(&c.stderr));
    assert_eq!(last_json(&c)["optimal_max_depth"], 2);
    assert!(last_json(&c)["optimal_depth"].is_null());
    let bad = omis(&[&common[..], &["--optimal-max-depth", "deep"]].concat());
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("neither `auto` nor a depth"));
}

#[test]
fn pbrt_and_mitsuba_scenes_render_through_the_service_with_their_files() {
    let Some(shared) = common::shared_scenes(
        "pbrt_and_mitsuba_scenes_render_through_the_service_with_their_files",
    ) else {
        return;
    };
    let d = folder("formats");
    // veach-bidir reads binary PLY meshes beside it: the bundle must carry them.
    for (k, scene) in [
        "veach-bidir/pbrt-v3/scene.pbrt",
        "veach-mis/mitsuba/scene.xml",
    ]
    .iter()
    .enumerate()
    {
        let path = shared.join(scene);
        let svc = d.join(format!("svc{k}.exr"));
        let inp = d.join(format!("inp{k}.exr"));
        let common = [
            "render",
            s(&path),
            "--spp",
            "2",
            "--max-depth",
            "3",
            "--resolution",
            "32x24",
        ];
        both_modes(&common, &svc, &inp);
        let ia = omis::film::image::exr_io::read_exr(&svc).expect("service EXR");
        let ib = omis::film::image::exr_io::read_exr(&inp).expect("in-process EXR");
        assert_eq!(ia, ib, "{scene}");
        assert!(
            ia.mean().iter().sum::<f64>() > 0.0,
            "{scene} rendered black"
        );
    }
}

#[test]
fn compare_reports_error_time_and_memory_at_equal_spp_and_equal_time() {
    let d = folder("compare");
    let reference = d.join("ref.exr");
    let out = omis(&[
        "render",
        "scenes/cornell-box-small-light.json",
        "--in-process",
        "--resolution",
        "24x24",
        "--spp",
        "256",
        "--integrator",
        "pt",
        "--out",
        s(&reference),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let outdir = d.join("out");
    let out = omis(&[
        "compare",
        "scenes/cornell-box-small-light.json",
        "--reference",
        s(&reference),
        "--spp",
        "1,8",
        "--mis",
        "balance,optimal,optimal-progressive",
        "--seeds",
        "2",
        "--threads",
        "1",
        "--equal-time",
        "0.3",
        "--out",
        s(&outdir),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j = last_json(&out);
    let file: serde_json::Value =
        serde_json::from_slice(&std::fs::read(outdir.join("results.json")).expect("results.json"))
            .expect("results.json is JSON");
    assert_eq!(j, file, "stdout and results.json agree");
    let points = j["equal_spp"].as_array().expect("equal_spp");
    assert_eq!(points.len(), 6, "2 spp x 3 strategies");
    assert_eq!(j["equal_time_clock"], "wall");
    // `--optimal-max-depth auto` (the default): every optimal render runs its pilot.
    assert_eq!(j["optimal_max_depth"], "auto");
    // BDPT's roulette is `omis render`'s default.
    assert_eq!(
        j["roulette_from"],
        omis::integrator::bdpt::ROULETTE_FROM,
        "{j}"
    );
    // Each optimal render's pilot: its choice per seed, its CPU time counted in the render's.
    let timed = j["equal_time"].as_array().expect("equal_time");
    assert_eq!(timed.len(), 3, "{j}");
    for p in points.iter().chain(timed) {
        let choices = p["optimal_depth"].as_array().expect("optimal_depth");
        let pilot = p["pilot_cpu_seconds"].as_f64().expect("pilot_cpu_seconds");
        if p["method"] == "balance" {
            assert!(choices.is_empty() && pilot == 0.0, "{p}");
        } else {
            assert_eq!(choices.len(), 2, "{p}");
            assert!(choices.iter().all(|c| c["chosen"].is_u64()), "{p}");
            assert!(
                pilot > 0.0 && pilot < p["cpu_seconds"].as_f64().expect("cpu"),
                "{p}"
            );
        }
    }
    // At equal time the pilot is a bounded share of the 0.3 s budget (4.7 ms): a smaller frame
    // than the whole 24x24 one a job of unknown size would take.
    for p in &timed[1..] {
        let c = &p["optimal_depth"][0]["pilot_resolution"];
        let px = c[0].as_u64().unwrap_or(0) * c[1].as_u64().unwrap_or(0);
        assert!(px > 0 && px < 24 * 24, "{p}");
    }
    let get = |m: &str, spp: u64| {
        points
            .iter()
            .find(|p| p["method"] == m && p["spp"] == spp)
            .unwrap_or_else(|| panic!("no {m} at {spp} spp"))
    };
    for p in points {
        let f = |k: &str| p[k].as_f64().unwrap_or_else(|| panic!("{k} in {p}"));
        assert!(f("relmse") > 0.0 && f("relmse_trimmed") > 0.0, "{p}");
        assert!(f("relmse_trimmed") <= f("relmse"), "{p}");
        assert!(f("seconds") > 0.0 && f("cpu_seconds") > 0.0, "{p}");
        assert_eq!(
            p["relmse_per_depth"].as_array().expect("per depth").len(),
            6
        );
    }
    for m in ["balance", "optimal", "optimal-progressive"] {
        // Eight times the samples: several times lower error (an unbiased estimator's relMSE
        // falls as 1/spp; a wide margin against the noise of two seeds).
        let (lo, hi) = (get(m, 8)["relmse"].as_f64(), get(m, 1)["relmse"].as_f64());
        assert!(
            lo.expect("relmse") * 3.0 < hi.expect("relmse"),
            "{m}: {lo:?} vs {hi:?}"
        );
    }
    assert!(
        get("optimal", 1)["bytes_per_pixel"].as_u64()
            > get("balance", 1)["bytes_per_pixel"].as_u64(),
        "optimal MIS keeps per-pixel systems"
    );
    // The progressive estimator's first pass is balance: at 1 spp it has balance's error (to
    // the rounding of the two ways of computing the balance weights).
    let (p1, b1) = (
        get("optimal-progressive", 1)["relmse"]
            .as_f64()
            .expect("relmse"),
        get("balance", 1)["relmse"].as_f64().expect("relmse"),
    );
    assert!((p1 / b1 - 1.0).abs() < 1e-3, "{p1} vs {b1}");
    let timed = j["equal_time"].as_array().expect("equal_time");
    assert_eq!(timed.len(), 3);
    for p in timed {
        assert!(p["spp"].as_u64().expect("spp") >= 1, "{p}");
        let wall = p["seconds"].as_f64().expect("seconds");
        let cpu = p["cpu_seconds"].as_f64().expect("cpu_seconds");
        // About the budget of wall time (the last pass is fitted to the time left, so it may
        // end a little before it); one thread, so CPU time cannot exceed it by much.
        assert!(wall >= 0.2 && cpu > 0.0 && cpu <= wall * 1.5 + 0.1, "{p}");
    }
    for f in [
        "relmse_vs_spp.svg",
        "gain_per_depth.svg",
        "time_overhead.svg",
        "memory.svg",
    ] {
        let text = std::fs::read_to_string(outdir.join(f)).expect(f);
        assert!(
            text.starts_with("<svg") && text.trim_end().ends_with("</svg>"),
            "{f}"
        );
    }
    // The table goes to stderr with --json: both strategies and the equal-time rows.
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("optimal") && err.contains("equal time"),
        "{err}"
    );
    // --cpu-time: the budget counts the process's CPU seconds.
    let out = omis(&[
        "compare",
        "scenes/cornell-box-small-light.json",
        "--reference",
        s(&reference),
        "--spp",
        "1",
        "--mis",
        "balance",
        "--seeds",
        "1",
        "--threads",
        "1",
        "--equal-time",
        "0.3",
        "--cpu-time",
        "--out",
        s(&d.join("out-cpu")),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j = last_json(&out);
    assert_eq!(j["equal_time_clock"], "CPU");
    let p = &j["equal_time"][0];
    let cpu = p["cpu_seconds"].as_f64().expect("cpu_seconds");
    let wall = p["seconds"].as_f64().expect("seconds");
    // About the budget of CPU time (the last pass fitted to the time left).
    assert!(cpu >= 0.2 && wall > 0.0, "{p}");
    // The flag without the mode it sets is refused.
    let out = omis(&[
        "compare",
        "scenes/cornell-box-small-light.json",
        "--reference",
        s(&reference),
        "--cpu-time",
    ]);
    assert_one_line_error(&out, "--equal-time");
    let out = omis(&[
        "compare",
        "scenes/cornell-box-small-light.json",
        "--reference",
        s(&reference),
        "--roulette-from",
        "0",
    ]);
    assert_one_line_error(&out, "--roulette-from");
}

#[test]
fn diff_and_compare_read_the_exr_header_before_the_pixels() {
    let d = folder("bomb");
    // A real 8x8 EXR whose header then claims a 20000x20000 data window.
    let small = d.join("small.exr");
    let img = omis::film::Image::new(8, 8);
    omis::film::image::exr_io::write_exr(&small, &img, &[], &[]).expect("write EXR");
    let mut bytes = std::fs::read(&small).expect("read");
    let key = b"dataWindow\0box2i\0";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("a dataWindow attribute")
        + key.len()
        + 4;
    for (k, v) in [0i32, 0, 19999, 19999].iter().enumerate() {
        bytes[at + 4 * k..at + 4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
    let bomb = d.join("bomb.exr");
    std::fs::write(&bomb, &bytes).expect("write");
    let start = std::time::Instant::now();
    assert_one_line_error(&omis(&["diff", s(&bomb), s(&small)]), "20000x20000");
    assert_one_line_error(
        &omis(&["diff", s(&small), s(&bomb), "--layers"]),
        "20000x20000",
    );
    assert_one_line_error(
        &omis(&["compare", "scenes/furnace.json", "--reference", s(&bomb)]),
        "20000x20000",
    );
    assert!(start.elapsed() < std::time::Duration::from_secs(30));
}

#[test]
fn an_image_diffed_with_itself_has_no_error_also_on_black_pixels() {
    let d = folder("self-diff");
    let path = d.join("half-black.exr");
    let mut img = omis::film::Image::new(8, 8);
    for (k, p) in img.pixels.iter_mut().enumerate().skip(32) {
        *p = omis::geometry::Rgb::splat(k as f32 * 0.1);
    }
    omis::film::image::exr_io::write_exr(&path, &img, &[], &[]).expect("write EXR");
    let out = omis(&["diff", s(&path), s(&path), "--eps", "0", "--json"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v = last_json(&out);
    assert_eq!(v["relmse"], 0.0, "{v}");
    assert_eq!(v["identical"], true, "{v}");
}

#[test]
fn bundle_writes_the_scene_and_every_file_its_importer_read() {
    let dir = folder("bundle");
    let out = dir.join("textures.tar");
    let o = omis(&["bundle", "scenes/mitsuba3/textures.xml", "--out", s(&out)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(last_json(&o)["main"], "textures.xml");
    let file = std::fs::File::open(&out).expect("bundle written");
    let mut names: Vec<String> = tar::Archive::new(file)
        .entries()
        .expect("a tar")
        .map(|e| {
            let e = e.expect("entry");
            e.path().expect("path").to_string_lossy().into_owned()
        })
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["parts/room.xml", "textures.xml", "textures/grid.png"]
    );
    let bad = omis(&[
        "bundle",
        "scenes/mitsuba3/textures.xml",
        "--out",
        s(&out),
        "--define",
        "novalue",
    ]);
    assert_one_line_error(&bad, "--define");
    let missing = omis(&["bundle", "no/such/scene.xml", "--out", s(&out)]);
    assert_one_line_error(&missing, "no/such/scene.xml");
}
