//! What a job writes beside its database rows: preview.png, error.png (with a reference) and
//! image.exr, between passes and at its end.

use super::App;
use super::error::{ServiceError, ServiceResult};
use super::runtime::Runtime;
use super::store::{JobRow, write_atomic};
use crate::film::Image;
use crate::film::format::merge_stream;
use crate::film::image::{error_map, exr_io, png};

/// What a job's outputs write of its image.exr.
pub(crate) enum Exr<'a> {
    /// Nothing (not due).
    No,
    /// The beauty alone, stored uncompressed: between passes, until the final one replaces it
    /// (`exr_io::ExrLayout::uncompressed` says why).
    Interim,
    /// The beauty and these layers, compressed here.
    Images(&'a [(String, Image)]),
    /// Every block of the file, compressed by the last pass's merge tasks (`film::merge_task`).
    Blocks(Vec<Vec<u8>>),
}

/// Writes preview.png, (with a reference) error.png and image.exr as `exr` says: made durable
/// before it replaces the last one.
pub(crate) fn write_outputs(
    app: &App,
    job: &JobRow,
    rt: &Runtime,
    image: &Image,
    exr: Exr,
) -> ServiceResult<()> {
    let preview = png::encode_rgb8(image.width, image.height, &png::to_srgb8(image, 0.0))
        .map_err(ServiceError::job)?;
    write_atomic(&app.paths.output(&job.id, "preview.png"), &preview)?;
    if let Some(r) = &rt.reference {
        let pic =
            error_map::error_picture(image, r, rt.resolved.eps, None).map_err(ServiceError::job)?;
        let bytes = png::encode_rgb8(pic.width, pic.height, &pic.rgb).map_err(ServiceError::job)?;
        write_atomic(&app.paths.output(&job.id, "error.png"), &bytes)?;
    }
    let r = &rt.resolved;
    let mut attrs = r.exr_attributes(&job.scene_main, job.spp_done);
    attrs.push(("omis.job", job.id.clone()));
    let tmp = app.paths.output(&job.id, "image.exr.tmp");
    match exr {
        Exr::No => return Ok(()),
        Exr::Interim => {
            exr_io::write_exr_uncompressed(&tmp, image, &[], &attrs).map_err(ServiceError::job)?
        }
        Exr::Images(layers) => {
            let named: Vec<exr_io::NamedLayer> = layers
                .iter()
                .map(|(name, image)| exr_io::NamedLayer {
                    name: name.clone(),
                    image,
                })
                .collect();
            let lines = exr_io::block_lines(r.tile_size);
            exr_io::write_exr_in_blocks(&tmp, image, &named, &attrs, lines)
                .map_err(ServiceError::job)?;
        }
        Exr::Blocks(blocks) => merge_stream::exr_layout(&r.grid(), &r.film_layout())
            .map_err(ServiceError::job)?
            .write(&tmp, &attrs, blocks)
            .map_err(ServiceError::job)?,
    }
    // Durable before it replaces the last one: the final EXR stands for a job's last pass.
    std::fs::File::open(&tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| ServiceError::job(format!("cannot sync {}: {e}", tmp.display())))?;
    Ok(std::fs::rename(
        &tmp,
        app.paths.output(&job.id, "image.exr"),
    )?)
}
