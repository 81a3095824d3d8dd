//! How long a job's passes are and how large its tiles: what bounds the photon maps a pass
//! holds, what the coordinator spends per task, and how many tasks a pass has.

use super::{FieldError, Limits};

/// Default samples of the first pass: the first preview after 16 spp.
pub const DEFAULT_PASS_SIZE: u32 = 16;
/// Default longest pass: passes double from `DEFAULT_PASS_SIZE` up to this, so that a job's
/// merges grow as O(log spp) rather than O(spp), and light-tracing records per task stay bounded.
pub const DEFAULT_MAX_PASS_SIZE: u32 = 256;
/// VCM and BPM: every process that renders a pass holds the photon map of each of its
/// iterations at once (a map keeps the iteration's light subpaths and photons: 591 bytes per
/// pixel on SmallVCM's scene 2 at depth 9, BENCHMARKS.md, "BDPT and VCM against SmallVCM"), so their passes are kept short
/// enough that a pass's maps fit in this many bytes, at `PHOTON_MAP_BYTES_PER_PIXEL` a map.
pub const PHOTON_PASS_BYTES: u64 = 4 << 30;
/// What a photon map is assumed to take per pixel when passes are limited (about twice what
/// SmallVCM's scene 2 takes).
pub const PHOTON_MAP_BYTES_PER_PIXEL: u64 = 1024;

/// VCM's and BPM's (first pass, longest pass): the settings', each at most the largest power of
/// two of iterations whose photon maps fit in `PHOTON_PASS_BYTES` (at least 1).
pub fn photon_passes(width: u32, height: u32, pass_size: u32, max_pass_size: u32) -> (u32, u32) {
    let per_map = (width as u64 * height as u64 * PHOTON_MAP_BYTES_PER_PIXEL).max(1);
    let fit = (PHOTON_PASS_BYTES / per_map).clamp(1, 1 << 16) as u32;
    let limit = 1 << fit.ilog2();
    let first = pass_size.min(limit);
    (first, max_pass_size.max(first).min(limit))
}

/// Tile edge of frames with fewer than `LARGE_TILE_MIN_TASKS` tiles of `LARGE_TILE_SIZE`.
pub const DEFAULT_TILE_SIZE: u32 = 32;
/// Tile edge of large frames: a task of 4x the pixels costs the coordinator about what a small
/// one does (1080p path tracing: 26 % less coordinator CPU, BDPT: 10-18 % fewer bytes per
/// sample; BENCHMARKS.md, "The render service").
pub const LARGE_TILE_SIZE: u32 = 64;
/// Tasks per pass a frame must have in tiles of `LARGE_TILE_SIZE` to get them (1024x1024 and
/// up), so that a pass still keeps dozens of workers busy.
pub const LARGE_TILE_MIN_TASKS: u64 = 256;
/// Tile edge of large frames for jobs whose pixels hold no optimal-MIS systems (the path
/// tracer, BDPT with the balance or power heuristic): their tasks are short and light, so a task
/// of 4x the pixels cuts what the coordinator spends per pixel sample by a quarter to a third
/// (1080p: PT 2.8 -> 1.8 %, BDPT balance 1.8 -> 1.4 % of the workers' CPU; BDPT's light-tracing
/// splats aggregate per pixel, 10.7 -> 8.6 bytes per pixel sample; BENCHMARKS.md, "The render service"). Optimal-MIS
/// tasks keep `LARGE_TILE_SIZE`: their systems (up to 1.3 kB a pixel) and records make a task
/// of this size heavy for the workers, and the coordinator gains less.
pub const HUGE_TILE_SIZE: u32 = 128;
/// Tasks per pass a frame must have in tiles of `HUGE_TILE_SIZE` to get them (1920x1080 and
/// up): a job queues two passes at once, so a pass of 128 tasks keeps a farm of 100 busy.
pub const HUGE_TILE_MIN_TASKS: u64 = 128;

/// The tile edge of a job that does not set one: `HUGE_TILE_SIZE` for a `light` job (no
/// optimal-MIS systems: `JobSettings::light_pixels`) whose frame has at least
/// `HUGE_TILE_MIN_TASKS` such tiles, else `LARGE_TILE_SIZE` where the frame has at least
/// `LARGE_TILE_MIN_TASKS` such tiles, else `DEFAULT_TILE_SIZE`.
pub fn auto_tile_size(width: u32, height: u32, light: bool) -> u32 {
    let tiles = |size: u32| {
        let size = size as u64;
        (width as u64).div_ceil(size) * (height as u64).div_ceil(size)
    };
    if light && tiles(HUGE_TILE_SIZE) >= HUGE_TILE_MIN_TASKS {
        HUGE_TILE_SIZE
    } else if tiles(LARGE_TILE_SIZE) >= LARGE_TILE_MIN_TASKS {
        LARGE_TILE_SIZE
    } else {
        DEFAULT_TILE_SIZE
    }
}

/// Refuses a frame of more than `limits.max_tasks_per_pass` tiles (field `tile_size`).
pub(super) fn check_tiles(
    width: u32,
    height: u32,
    tile: u32,
    limits: &Limits,
) -> Result<(), FieldError> {
    let tiles = |t: u64| (width as u64).div_ceil(t) * (height as u64).div_ceil(t);
    let max = limits.max_tasks_per_pass as u64;
    if tiles(tile.max(1) as u64) <= max {
        return Ok(());
    }
    let smallest = (1..=width.max(height) as u64)
        .find(|&t| tiles(t) <= max)
        .unwrap_or(width.max(height) as u64);
    Err(FieldError::new(
        "tile_size",
        format!(
            "{width}x{height} in tiles of {tile} is {} tasks per pass, more than the limit of \
             {max} (max_tasks_per_pass); use a tile_size of at least {smallest}",
            tiles(tile.max(1) as u64)
        ),
    ))
}
