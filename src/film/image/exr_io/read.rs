//! Reading EXR files: every layer at once, or the beauty alone block by block (whatever the
//! file's size, memory holds one block).

use super::ExrError;
use crate::film::Image;
use crate::geometry::Rgb;
use exr::meta::attribute::SampleType;
use exr::meta::header::Header;
use exr::prelude::read_all_flat_layers_from_file;
use std::path::Path;

/// Reads the layers of an EXR file: the beauty (`R, G, B` or `Y`) and every `<name>.R/G/B` group.
/// Returns (layer name, image) pairs; the beauty layer has the empty name.
pub fn read_exr_layers(path: &Path) -> Result<Vec<(String, Image)>, ExrError> {
    let img = read_all_flat_layers_from_file(path).map_err(|source| ExrError::Unreadable {
        path: path.to_path_buf(),
        source,
    })?;
    let mut out: Vec<(String, Image)> = Vec::new();
    for layer in &img.layer_data {
        let (w, h) = (layer.size.0, layer.size.1);
        let part = layer
            .attributes
            .layer_name
            .as_ref()
            .map(|t| t.to_string())
            .unwrap_or_default();
        let part = if part == "omis" { String::new() } else { part };
        let mut groups: Vec<(String, [Option<Vec<f32>>; 3])> = Vec::new();
        for ch in &layer.channel_data.list {
            let name = ch.name.to_string();
            let (prefix, comp) = match name.rsplit_once('.') {
                Some((p, c)) => (p.to_string(), c.to_string()),
                None => (String::new(), name.clone()),
            };
            let slot = match comp.as_str() {
                "R" | "r" => 0,
                "G" | "g" => 1,
                "B" | "b" => 2,
                "Y" | "y" => 3,
                _ => continue,
            };
            let full_prefix = match (part.is_empty(), prefix.is_empty()) {
                (true, _) => prefix,
                (false, true) => part.clone(),
                (false, false) => format!("{part}.{prefix}"),
            };
            let values: Vec<f32> = ch.sample_data.values_as_f32().collect();
            let entry = match groups.iter_mut().position(|(p, _)| *p == full_prefix) {
                Some(i) => &mut groups[i].1,
                None => {
                    groups.push((full_prefix, [None, None, None]));
                    &mut groups.last_mut().expect("just pushed").1
                }
            };
            if slot == 3 {
                entry[0] = Some(values.clone());
                entry[1] = Some(values.clone());
                entry[2] = Some(values);
            } else {
                entry[slot] = Some(values);
            }
        }
        for (name, [r, g, b]) in groups {
            if let (Some(r), Some(g), Some(b)) = (r, g, b) {
                let mut im = Image::new(w, h);
                for i in 0..w * h {
                    im.pixels[i] = Rgb::new(r[i], g[i], b[i]);
                }
                out.push((name, im));
            }
        }
    }
    if out.is_empty() {
        return Err(ExrError::NoBeauty {
            path: path.to_path_buf(),
        });
    }
    Ok(out)
}

/// Reads the beauty layer (or the first RGB layer) of an EXR file.
pub fn read_exr(path: &Path) -> Result<Image, ExrError> {
    let mut layers = read_exr_layers(path)?;
    let i = layers.iter().position(|(n, _)| n.is_empty()).unwrap_or(0);
    Ok(layers.swap_remove(i).1)
}

/// The channels of the layer `read_exr` reads: its part, and the channel index of R, G and B
/// (a `Y` channel stands for all three).
struct BeautyChannels {
    part: usize,
    rgb: [usize; 3],
}

/// Finds the layer `read_exr` would return, from the headers alone: the group of channels with
/// the empty name, else the first complete R, G, B group in file order.
fn beauty_channels(headers: &[Header]) -> Option<BeautyChannels> {
    let mut groups: Vec<(String, usize, [Option<usize>; 3])> = Vec::new();
    for (part, h) in headers.iter().enumerate() {
        let name = h
            .own_attributes
            .layer_name
            .as_ref()
            .map(|t| t.to_string())
            .unwrap_or_default();
        let name = if name == "omis" { String::new() } else { name };
        for (c, ch) in h.channels.list.iter().enumerate() {
            let full = ch.name.to_string();
            let (prefix, comp) = full.rsplit_once('.').unwrap_or(("", full.as_str()));
            let slots: &[usize] = match comp {
                "R" | "r" => &[0],
                "G" | "g" => &[1],
                "B" | "b" => &[2],
                "Y" | "y" => &[0, 1, 2],
                _ => continue,
            };
            let group = match (name.is_empty(), prefix.is_empty()) {
                (true, _) => prefix.to_string(),
                (false, true) => name.clone(),
                (false, false) => format!("{name}.{prefix}"),
            };
            let k = match groups
                .iter()
                .position(|(g, p, _)| *g == group && *p == part)
            {
                Some(k) => k,
                None => {
                    groups.push((group, part, [None; 3]));
                    groups.len() - 1
                }
            };
            for &slot in slots {
                groups[k].2[slot] = Some(c);
            }
        }
    }
    let complete = |g: &&(String, usize, [Option<usize>; 3])| g.2.iter().all(Option::is_some);
    let pick = groups
        .iter()
        .filter(complete)
        .find(|g| g.0.is_empty())
        .or_else(|| groups.iter().find(complete))?;
    Some(BeautyChannels {
        part: pick.1,
        rgb: pick.2.map(|c| c.unwrap_or(0)),
    })
}

/// Reads the beauty layer of the EXR at `path` (the layer `read_exr` reads) block by block:
/// `size(width, height)` first, then `line(x, y, component, values)` for every line of samples
/// (a scan line, or a tile's row) of each of its R, G, B components. Memory holds one block,
/// whatever the file's size.
pub fn for_each_beauty_line(
    path: &Path,
    size: impl FnOnce(usize, usize) -> Result<(), String>,
    mut line: impl FnMut(usize, usize, usize, &[f32]),
) -> Result<(), ExrError> {
    use exr::block::reader::ChunksReader;
    use exr::prelude::f16;
    let bad = |source| ExrError::Unreadable {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(|source| ExrError::File {
        path: path.to_path_buf(),
        source,
    })?;
    let reader = exr::block::read(std::io::BufReader::new(file), false).map_err(bad)?;
    let headers: Vec<Header> = reader.headers().to_vec();
    let beauty = beauty_channels(&headers).ok_or_else(|| ExrError::NoBeauty {
        path: path.to_path_buf(),
    })?;
    let header = &headers[beauty.part];
    let (w, h) = (header.layer_size.width(), header.layer_size.height());
    size(w, h).map_err(ExrError::Refused)?;
    let part = beauty.part;
    let chunks = reader
        .filter_chunks(false, |_, _, block| {
            block.layer == part && block.level == exr::math::Vec2(0, 0)
        })
        .map_err(bad)?;
    let blocks = chunks.sequential_decompressor(false);
    let mut values: Vec<f32> = Vec::new();
    for block in blocks {
        let block = block.map_err(bad)?;
        for l in block.lines(&header.channels) {
            let loc = l.location;
            if !beauty.rgb.contains(&loc.channel) {
                continue;
            }
            values.clear();
            match header.channels.list[loc.channel].sample_type {
                SampleType::F32 => {
                    for v in l.read_samples::<f32>() {
                        values.push(v.map_err(bad)?);
                    }
                }
                SampleType::F16 => {
                    for v in l.read_samples::<f16>() {
                        values.push(v.map_err(bad)?.to_f32());
                    }
                }
                SampleType::U32 => {
                    for v in l.read_samples::<u32>() {
                        values.push(v.map_err(bad)? as f32);
                    }
                }
            }
            let (x, y) = (loc.position.x(), loc.position.y());
            if x + values.len() > w || y >= h {
                return Err(ExrError::Layout(format!(
                    "{}: a block of the beauty holds {} values at ({x}, {y}), outside its {w}x{h} \
                     layer",
                    path.display(),
                    values.len()
                )));
            }
            for k in (0..3).filter(|&k| beauty.rgb[k] == loc.channel) {
                line(x, y, k, &values);
            }
        }
    }
    Ok(())
}

/// The width and height of the beauty layer of the EXR at `path` (the layer `read_exr` reads),
/// from its headers alone.
pub fn beauty_size(path: &Path) -> Result<(usize, usize), ExrError> {
    let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|source| {
        ExrError::Unreadable {
            path: path.to_path_buf(),
            source,
        }
    })?;
    let beauty = beauty_channels(&meta.headers).ok_or_else(|| ExrError::NoBeauty {
        path: path.to_path_buf(),
    })?;
    let size = meta.headers[beauty.part].layer_size;
    Ok((size.width(), size.height()))
}

/// The beauty layer of an EXR (as `read_exr` reads it), read block by block into one image:
/// the file's other layers never take memory.
pub fn read_exr_beauty(path: &Path) -> Result<Image, ExrError> {
    let img = std::cell::RefCell::new(Image::new(0, 0));
    for_each_beauty_line(
        path,
        |w, h| {
            *img.borrow_mut() = Image::new(w, h);
            Ok(())
        },
        |x, y, k, values| {
            let mut img = img.borrow_mut();
            let at = y * img.width + x;
            for (p, v) in img.pixels[at..at + values.len()].iter_mut().zip(values) {
                p[k] = *v;
            }
        },
    )?;
    Ok(img.into_inner())
}
