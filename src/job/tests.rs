//! Unit tests of the settings: validation, resolution, pass and tile sizes, budgets.

use super::*;
use crate::integrator::RenderSettings;

/// A VCM or BPM pass holds one photon map per iteration in every process that renders it:
/// passes are cut to what fits in `PHOTON_PASS_BYTES`; other integrators keep theirs.
#[test]
fn photon_passes_fit_the_memory_budget() {
    assert_eq!(photon_passes(512, 512, 16, 256), (16, 16));
    assert_eq!(photon_passes(512, 512, 1, 4), (1, 4));
    assert_eq!(photon_passes(1920, 1080, 16, 256), (2, 2));
    assert_eq!(photon_passes(3840, 2160, 16, 256), (1, 1));
    assert_eq!(photon_passes(64, 64, 16, 256), (16, 256));
    for (w, h) in [(1, 1), (512, 512), (1920, 1080), (65536, 65536)] {
        let (first, max) = photon_passes(w, h, 16, 256);
        assert!(first >= 1 && max >= first && max.is_power_of_two());
        let maps = max as u64 * w as u64 * h as u64 * PHOTON_MAP_BYTES_PER_PIXEL;
        assert!(max == 1 || maps <= PHOTON_PASS_BYTES, "{w}x{h}: {max}");
    }
    let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/cornell-box.json"
    )))
    .expect("the Cornell box");
    for (integrator, pass) in [
        (IntegratorKind::Vcm, Some(16)),
        (IntegratorKind::Bpm, Some(16)),
        (IntegratorKind::Bdpt, Some(256)),
    ] {
        let job = JobSettings {
            resolution: Some([512, 512]),
            spp: Some(64),
            integrator,
            ..Default::default()
        };
        let r = job
            .resolve(&mut scene, &Limits::default())
            .expect("resolves");
        assert_eq!(r.max_pass_size, pass, "{integrator:?}");
    }
}

#[test]
fn roulette_defaults_per_integrator_and_is_recorded_in_the_exr() {
    let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/cornell-box.json"
    )))
    .expect("the Cornell box");
    let bdpt_from = integrator::bdpt::ROULETTE_FROM;
    // (integrator, roulette, roulette_from) -> the start vertex, None without roulette.
    let cases = [
        (IntegratorKind::Vcm, None, None, Some(1)),
        (IntegratorKind::Vcm, Some(false), None, None),
        (IntegratorKind::Bdpt, None, None, Some(bdpt_from)),
        (IntegratorKind::Bdpt, Some(false), None, None),
        (IntegratorKind::Bdpt, Some(true), Some(1), Some(1)),
        (IntegratorKind::Bdpt, None, Some(7), Some(7)),
        (IntegratorKind::Bpm, None, None, None),
        (IntegratorKind::Bpm, None, Some(1), Some(1)),
        (IntegratorKind::Pt, None, None, None),
    ];
    for (integrator, roulette, roulette_from, want) in cases {
        let job = JobSettings {
            resolution: Some([64, 64]),
            spp: Some(4),
            integrator,
            roulette,
            roulette_from,
            ..Default::default()
        };
        let r = job
            .resolve(&mut scene, &Limits::default())
            .expect("resolves");
        let case = format!("{integrator:?} {roulette:?} {roulette_from:?}");
        if integrator != IntegratorKind::Pt {
            assert_eq!(r.render.roulette_start(), want, "{case}");
        }
        let attributes = r.exr_attributes("cornell-box", 4);
        let attribute = |name: &str| {
            attributes
                .iter()
                .find(|(k, _)| *k == name)
                .map(|(_, v)| v.clone())
        };
        let expected = (integrator != IntegratorKind::Pt)
            .then(|| (if want.is_some() { "on" } else { "off" }).to_string());
        assert_eq!(attribute("omis.roulette"), expected, "{case}");
        assert_eq!(
            attribute("omis.roulette_from"),
            want.map(|n| n.to_string()),
            "{case}"
        );
    }
    // A job stored before the field was optional reads back as what it said.
    let old: JobSettings =
        serde_json::from_str(r#"{"integrator": "vcm", "roulette": false}"#).expect("parses");
    assert_eq!(old.roulette, Some(false));
    // Render settings from before `roulette_from` meant roulette at every vertex.
    let new = serde_json::to_string(&RenderSettings {
        roulette: true,
        roulette_from: 5,
        ..Default::default()
    })
    .expect("serialises");
    let field = ",\"roulette_from\":5";
    assert!(new.contains(field), "{new}");
    let old: RenderSettings = serde_json::from_str(&new.replace(field, "")).expect("parses");
    assert_eq!(old.roulette_start(), Some(1));
    // Starts outside 1 ..= 64, or with roulette off, are refused by name.
    for (integrator, roulette, from) in [
        (IntegratorKind::Bdpt, None, 0),
        (IntegratorKind::Bdpt, None, 65),
        (IntegratorKind::Bdpt, Some(false), 3),
        (IntegratorKind::Vcm, None, 2),
        (IntegratorKind::Bpm, Some(true), 4),
    ] {
        let job = JobSettings {
            integrator,
            roulette,
            roulette_from: Some(from),
            ..Default::default()
        };
        let e = job.validate(&Limits::default()).expect_err("refused");
        assert_eq!(
            e.field, "roulette_from",
            "{integrator:?} {roulette:?} {from}"
        );
    }
}

#[test]
fn tiles_grow_with_the_frame_unless_set() {
    for light in [false, true] {
        assert_eq!(auto_tile_size(512, 512, light), DEFAULT_TILE_SIZE);
        assert_eq!(auto_tile_size(1280, 720, light), DEFAULT_TILE_SIZE); // 240 large tiles
        assert_eq!(auto_tile_size(1024, 1024, light), LARGE_TILE_SIZE); // 256, 64 huge
        assert_eq!(auto_tile_size(0, 0, light), DEFAULT_TILE_SIZE);
    }
    // 1080p: 510 large tiles, 135 huge ones; huge only where no systems are kept.
    assert_eq!(auto_tile_size(1920, 1080, false), LARGE_TILE_SIZE);
    assert_eq!(auto_tile_size(1920, 1080, true), HUGE_TILE_SIZE);
    let job = |integrator, mis| JobSettings {
        integrator,
        mis,
        ..JobSettings::default()
    };
    let (pt, bdpt) = (IntegratorKind::Pt, IntegratorKind::Bdpt);
    assert_eq!(job(pt, MisKind::Balance).auto_tile_size(1920, 1080), 128);
    assert_eq!(job(bdpt, MisKind::Power).auto_tile_size(1920, 1080), 128);
    assert_eq!(job(bdpt, MisKind::Optimal).auto_tile_size(1920, 1080), 64);
    assert_eq!(
        job(bdpt, MisKind::OptimalProgressive).auto_tile_size(1920, 1080),
        64
    );
    assert_eq!(
        job(IntegratorKind::Vcm, MisKind::Balance).auto_tile_size(1920, 1080),
        64
    );
    // Resolved against the scene's frame; an explicit size wins, also where it is smaller.
    let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/cornell-box.json"
    )))
    .expect("scene");
    let l = Limits::default();
    let at = |res: [u32; 2], tile: Option<u32>, scene: &mut crate::scene::Scene| {
        JobSettings {
            resolution: Some(res),
            tile_size: tile,
            integrator: IntegratorKind::Pt,
            spp: Some(1),
            ..Default::default()
        }
        .resolve(scene, &l)
        .expect("resolves")
        .tile_size
    };
    assert_eq!(at([1920, 1080], None, &mut scene), 128); // the path tracer: light
    assert_eq!(at([640, 480], None, &mut scene), 32);
    assert_eq!(at([1920, 1080], Some(16), &mut scene), 16);
    // Stored settings from before the field was optional read back as what they said.
    let old: JobSettings = serde_json::from_str(r#"{"tile_size": 32}"#).expect("parses");
    assert_eq!(old.tile_size, Some(32));
}

#[test]
fn pass_ranges_cover_the_samples_once() {
    let mut r = Resolved {
        defines: SceneParams::default(),
        width: 4,
        height: 4,
        render: RenderSettings::default(),
        spp: Some(40),
        time_budget_s: None,
        budget_spp: None,
        pilot_s: None,
        tile_size: 2,
        pass_size: 16,
        max_pass_size: None,
        eps: 0.01,
        optimal_depth: None,
    };
    assert_eq!(r.total_passes(), Some(3));
    assert_eq!(r.pass_range(0), Some(0..16));
    assert_eq!(r.pass_range(2), Some(32..40));
    assert_eq!(r.pass_range(3), None);
    r.spp = None;
    assert_eq!(r.pass_range(7), Some(112..128));
    assert_eq!(r.total_passes(), None);
    // Growing passes: 16, 32, 64, 64, ... (a cap of 100 rounds down to 16 x 4).
    r.max_pass_size = Some(100);
    assert_eq!(
        (0..5).map(|p| r.pass_range(p)).collect::<Vec<_>>(),
        [
            Some(0..16),
            Some(16..48),
            Some(48..112),
            Some(112..176),
            Some(176..240)
        ]
    );
    // Every fixed spp is covered exactly once, by total_passes passes.
    for max in [None, Some(16), Some(17), Some(256), Some(65536)] {
        r.max_pass_size = max;
        for spp in [1, 15, 16, 17, 47, 48, 49, 1000, 4096, 1 << 20] {
            r.spp = Some(spp);
            let n = r.total_passes().expect("fixed spp");
            let mut next = 0;
            for p in 0..n {
                let range = r.pass_range(p).expect("a pass below total_passes");
                assert_eq!(range.start, next, "{max:?} {spp} pass {p}");
                assert!(range.end > range.start);
                next = range.end;
            }
            assert_eq!(next, spp, "{max:?} {spp}");
            assert_eq!(r.pass_range(n), None, "{max:?} {spp}");
        }
    }
    // Ranges past u32::MAX samples do not exist.
    r.spp = None;
    r.max_pass_size = Some(65536);
    assert_eq!(r.pass_range(u32::MAX), None);
}

/// A time-budget job rendered at a steady `seconds_per_spp`, pass after pass as the runners
/// do: its samples per pixel and the seconds it took.
fn budget_run(r: &Resolved, seconds_per_spp: f64) -> (u32, f64) {
    let mut job = r.clone();
    let (mut spp, mut t, mut p) = (0, 0.0, 0);
    while let Some(range) = job.fit_to_budget(p, t, spp as f64, seconds_per_spp) {
        assert_eq!(range.start, spp, "passes follow one another");
        t += seconds_per_spp * (range.end - range.start) as f64;
        spp = range.end;
        p += 1;
    }
    (spp, t)
}

#[test]
fn the_last_pass_is_fitted_to_the_time_budget() {
    let mut r = Resolved {
        defines: SceneParams::default(),
        width: 4,
        height: 4,
        render: RenderSettings::default(),
        spp: None,
        time_budget_s: Some(1.0),
        budget_spp: None,
        pilot_s: None,
        tile_size: 2,
        pass_size: 1,
        max_pass_size: Some(256),
        eps: 0.01,
        optimal_depth: None,
    };
    for (pass_size, max) in [(1, 256), (1, 4), (4, 64), (3, 48), (16, 16)] {
        r.pass_size = pass_size;
        r.max_pass_size = Some(max);
        for spp_in_budget in [0.3, 1.0, 1.6, 7.0, 100.0, 300.0, 511.0, 1000.5, 1e5] {
            let (spp, t) = budget_run(&r, 1.0 / spp_in_budget);
            let block = pass_size as f64 / spp_in_budget;
            if spp_in_budget <= pass_size as f64 {
                // The first pass is rendered whatever the budget.
                assert_eq!(spp, pass_size, "{pass_size} {max} {spp_in_budget}");
            } else {
                // The end nearest the budget that whole blocks allow.
                assert!(
                    (t - 1.0).abs() <= block / 2.0 + 1e-9,
                    "{pass_size} {max} {spp_in_budget}: {spp} spp, {t} s"
                );
            }
            // With a sample count as well, whichever comes first ends the job.
            let capped = Resolved {
                spp: Some(50),
                ..r.clone()
            };
            let (spp_c, _) = budget_run(&capped, 1.0 / spp_in_budget);
            assert_eq!(spp_c, spp.min(50).max(pass_size.min(50)));
        }
    }
    r.pass_size = 1;
    r.max_pass_size = Some(256);
    // The pilot's seconds count against the budget: a quarter of it leaves three quarters
    // for the passes.
    let piloted = Resolved {
        pilot_s: Some(0.25),
        ..r.clone()
    };
    let (spp, t) = budget_run(&piloted, 1.0 / 1000.0);
    assert!((t - 0.75).abs() <= 0.5 / 1000.0 + 1e-9, "{spp} spp, {t} s");
    // A budget that the passes so far have used up begins no further pass.
    assert_eq!(r.clone().fit_to_budget(3, 1.0, 7.0, 1.0 / 7.0), None);
    assert_eq!(r.clone().fit_to_budget(0, 5.0, 0.0, 0.0), Some(0..1));
    // Without a budget, or before any sample, the pass is the planned one.
    assert_eq!(r.clone().fit_to_budget(3, 0.0, 0.0, 0.0), Some(7..15));
    let fixed = Resolved {
        time_budget_s: None,
        spp: Some(100),
        ..r.clone()
    };
    assert_eq!(
        fixed.clone().fit_to_budget(3, 10.0, 7.0, 10.0 / 7.0),
        Some(7..15)
    );
    // The fitted count is stored only where it is set.
    let json = serde_json::to_string(&r).expect("serialises");
    assert!(!json.contains("budget_spp"), "{json}");
    let mut fitted = r.clone();
    assert_eq!(fitted.fit_to_budget(3, 0.5, 7.0, 0.5 / 7.0), Some(7..14));
    assert_eq!(fitted.budget_spp, Some(14));
    assert_eq!(fitted.total_passes(), Some(4));
    let back: Resolved =
        serde_json::from_str(&serde_json::to_string(&fitted).expect("serialises")).expect("parses");
    assert_eq!(back, fitted);
    // A fit whose pass was never begun (its tasks never made) is withdrawn when the pass is
    // not begun after all: the job's target is where it ends.
    assert_eq!(fitted.fit_to_budget(3, 1.5, 7.0, 0.5 / 7.0), None);
    assert_eq!(fitted.budget_spp, None);
    assert_eq!(fitted.total_passes(), None);
}

#[test]
fn the_in_process_runner_fits_its_last_pass_to_the_budget() {
    let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/cornell-box.json"
    )))
    .expect("the Cornell box");
    scene.camera = scene.camera.with_resolution(8, 8).expect("8x8");
    let settings = RenderSettings {
        max_depth: 2,
        ..RenderSettings::default()
    };
    // Passes of 1, 2, 4, ..., 64 samples; a clock that counts one second per sample per
    // pixel rendered (from the tasks done: the runner reads it between passes).
    let job = Resolved {
        max_pass_size: Some(64),
        ..Resolved::timed(&scene, &settings, 4, 1, 100.0)
    };
    let tiles = job.tiles().len();
    let tasks = std::sync::atomic::AtomicUsize::new(0);
    let clock = || {
        let passes = tasks.load(std::sync::atomic::Ordering::Relaxed) / tiles;
        passes
            .checked_sub(1)
            .and_then(|p| job.pass_range(p as u32))
            .map_or(0.0, |r| r.end as f64)
    };
    let out = job.render_in_process_clocked(
        &scene,
        &|n| {
            tasks.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
        },
        &clock,
    );
    // Not 127 (the pass of 64 begun at 63 s run to its end).
    assert_eq!(out.spp, 100);
}

#[test]
fn bad_settings_name_their_field() {
    let l = Limits::default();
    let cases = [
        (
            JobSettings {
                resolution: Some([0, 4]),
                ..Default::default()
            },
            "resolution",
        ),
        (
            JobSettings {
                resolution: Some([100000, 4]),
                ..Default::default()
            },
            "resolution",
        ),
        (
            JobSettings {
                spp: Some(0),
                ..Default::default()
            },
            "spp",
        ),
        (
            JobSettings {
                mis: MisKind::Optimal,
                ..Default::default()
            },
            "mis",
        ),
        (
            JobSettings {
                kappa: f64::NAN,
                ..Default::default()
            },
            "kappa",
        ),
        (
            JobSettings {
                tile_size: Some(0),
                ..Default::default()
            },
            "tile_size",
        ),
    ];
    for (s, field) in cases {
        assert_eq!(s.validate(&l).map_err(|e| e.field), Err(field.to_string()));
    }
    assert!(JobSettings::default().validate(&l).is_ok());
}

#[test]
fn unknown_fields_are_refused() {
    let e = serde_json::from_str::<JobSettings>(r#"{"spp": 4, "spq": 1}"#).unwrap_err();
    assert!(e.to_string().contains("spq"), "{e}");
    let s: JobSettings = serde_json::from_str(r#"{"spp": 4, "resolution": [8, 6]}"#).unwrap();
    assert_eq!(s.spp, Some(4));
    assert_eq!(s.resolution, Some([8, 6]));
}

/// Workers and stored jobs read `RenderSettings` by its JSON names: the sampler's block is
/// `spp` there.
#[test]
fn the_sample_block_is_spp_in_json() {
    let settings = RenderSettings {
        sample_block: 7,
        ..Default::default()
    };
    let json = serde_json::to_value(&settings).expect("serialises");
    assert_eq!(json["spp"], 7, "{json}");
    assert!(json.get("sample_block").is_none(), "{json}");
    let back: RenderSettings = serde_json::from_value(json).expect("parses");
    assert_eq!(back, settings);
}
