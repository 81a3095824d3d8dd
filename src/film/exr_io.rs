//! OpenEXR output and input with the pure-Rust `exr` crate.
//!
//! A render is written as one EXR part whose channels are `R, G, B` (the beauty layer) plus
//! `<layer>.R, <layer>.G, <layer>.B` for every extra named layer: the dotted naming that
//! OpenEXR, Nuke and Blender read as a multi-layer image.

use super::Image;
use crate::geometry::Rgb;
use exr::prelude::{
    AnyChannel, AnyChannels, AttributeValue, Encoding, FlatSamples, Layer, LayerAttributes, Text,
    WritableImage, read_all_flat_layers_from_file,
};
use std::path::Path;

/// A named RGB layer; the empty name is the beauty layer.
pub struct NamedLayer<'a> {
    /// The layer name (channels `<name>.R`, ...); empty for the beauty layer.
    pub name: String,
    /// The layer's pixels.
    pub image: &'a Image,
}

/// Writes `beauty` plus `extra` layers (all the same size) as 32-bit float channels, ZIP
/// compressed, with `attributes` stored as string header attributes.
pub fn write_exr(
    path: &Path,
    beauty: &Image,
    extra: &[NamedLayer],
    attributes: &[(&str, String)],
) -> Result<(), String> {
    let (w, h) = (beauty.width, beauty.height);
    let mut channels: Vec<AnyChannel<FlatSamples>> = Vec::new();
    let mut push = |prefix: &str, img: &Image| -> Result<(), String> {
        if img.width != w || img.height != h {
            return Err(format!(
                "layer '{prefix}' is {}x{}, beauty is {w}x{h}",
                img.width, img.height
            ));
        }
        for (c, name) in ["R", "G", "B"].iter().enumerate() {
            let data: Vec<f32> = img.pixels.iter().map(|p| p[c]).collect();
            let full = if prefix.is_empty() {
                name.to_string()
            } else {
                format!("{prefix}.{name}")
            };
            channels.push(AnyChannel::new(full.as_str(), FlatSamples::F32(data)));
        }
        Ok(())
    };
    push("", beauty)?;
    for l in extra {
        if l.name.is_empty() || l.name.contains(|c: char| c.is_control()) {
            return Err(format!("invalid layer name '{}'", l.name));
        }
        push(&l.name, l.image)?;
    }
    let mut attrs = LayerAttributes::named("omis");
    for (k, v) in attributes {
        attrs
            .other
            .insert(Text::from(*k), AttributeValue::Text(Text::from(v.as_str())));
    }
    let layer = Layer::new(
        (w, h),
        attrs,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(channels.into()),
    );
    Image_::from_layer(layer)
        .write()
        .to_file(path)
        .map_err(|e| format!("{}: cannot write EXR: {e}", path.display()))
}

type Image_<L> = exr::image::Image<L>;

/// Reads the layers of an EXR file: the beauty (`R, G, B` or `Y`) and every `<name>.R/G/B` group.
/// Returns (layer name, image) pairs; the beauty layer has the empty name.
pub fn read_exr_layers(path: &Path) -> Result<Vec<(String, Image)>, String> {
    let img = read_all_flat_layers_from_file(path)
        .map_err(|e| format!("{}: not a readable EXR: {e}", path.display()))?;
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
        return Err(format!("{}: EXR has no R, G, B channels", path.display()));
    }
    Ok(out)
}

/// Reads the beauty layer (or the first RGB layer) of an EXR file.
pub fn read_exr(path: &Path) -> Result<Image, String> {
    let mut layers = read_exr_layers(path)?;
    let i = layers.iter().position(|(n, _)| n.is_empty()).unwrap_or(0);
    Ok(layers.swap_remove(i).1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_with_layers() {
        let dir = std::env::temp_dir().join(format!("omis-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.exr");
        let mut a = Image::new(5, 3);
        let mut b = Image::new(5, 3);
        for (i, p) in a.pixels.iter_mut().enumerate() {
            *p = Rgb::new(i as f32 * 0.5, 1e-7 * i as f32, -(i as f32) + 1e6);
        }
        for (i, p) in b.pixels.iter_mut().enumerate() {
            *p = Rgb::splat(i as f32 / 7.0);
        }
        write_exr(
            &path,
            &a,
            &[NamedLayer {
                name: "variance".into(),
                image: &b,
            }],
            &[("omis.spp", "4".into())],
        )
        .unwrap();
        let layers = read_exr_layers(&path).unwrap();
        let beauty = &layers.iter().find(|(n, _)| n.is_empty()).unwrap().1;
        let var = &layers.iter().find(|(n, _)| n == "variance").unwrap().1;
        assert_eq!(beauty, &a);
        assert_eq!(var, &b);
        std::fs::remove_dir_all(&dir).ok();
    }
}
