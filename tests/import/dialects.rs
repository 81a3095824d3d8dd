//! The pbrt dialect of a file, and the files a scene reads.

use crate::common;
use crate::common::import::{assert_has, load, load_err, write_obj, write_plys, write_png};
use crate::support::folder;

#[test]
fn pbrt_v4_files_are_read_as_pbrt_v4_from_the_first_pbrt_v4_construct() {
    let d = folder("pbrt-v4");
    let head = "LookAt 0 0 5  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n";
    // Each body has one pbrt-v4 construct: the file loads as pbrt-v4 (the pbrt-v3 path would
    // have refused, tests/import_pbrt4.rs checks the pbrt-v4 meanings).
    let bodies = [
        "ColorSpace \"srgb\"\nWorldBegin",
        "Option \"bool disablepixeljitter\" true\nWorldBegin",
        "Film \"rgb\" \"integer xresolution\" 8\nWorldBegin",
        "Sampler \"zsobol\"\nWorldBegin",
        "WorldBegin\nMaterial \"diffuse\" \"rgb reflectance\" [ 0.5 0.5 0.5 ]\nShape \"sphere\"",
        "WorldBegin\nMakeNamedMaterial \"c\"\n  \"string type\" \"coateddiffuse\"\nNamedMaterial \"c\"",
        "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [ 0 0 0 1 0 0 0 1 0 1 1 0 ]",
        "WorldBegin\nAreaLightSource \"diffuse\" \"rgb L\" [ 1 1 1 ]\n  \"float scale\" 4\nShape \"sphere\"",
        "WorldBegin\nLightSource \"point\" \"float power\" 100",
    ];
    for (i, body) in bodies.iter().enumerate() {
        let name = format!("v4-{i}.pbrt");
        load(&common::write(&d, &name, &format!("{head}{body}\n")));
    }
    // `Attribute "shape"` sets a default every later shape of the block reads.
    let s = load(&common::write(
        &d,
        "v4-attribute.pbrt",
        &format!("{head}WorldBegin\nAttribute \"shape\" \"float radius\" 2\nShape \"sphere\"\n"),
    ));
    assert_eq!(s.spheres[0].radius, 2.0);
    // A pbrt-v4 file included from a pbrt-v3 one: read as pbrt-v4 from there on; its errors
    // name it.
    common::write(&d, "v4-part.pbrt", "# pbrt-v4\n\nShape \"bilinearmesh\"\n");
    let e = load_err(&common::write(
        &d,
        "v3-main.pbrt",
        &format!("{head}WorldBegin\nInclude \"v4-part.pbrt\"\nWorldEnd\n"),
    ));
    assert_has(
        &e,
        &["v4-part.pbrt", "line 3", "bilinearmesh has no \"point3 P\""],
    );
    // A whole pbrt-v4 scene (as pbrt-v4 writes them: no WorldEnd) is read as such: the missing
    // mesh is what fails.
    let e = load_err(&common::write(
        &d,
        "v4-scene.pbrt",
        "LookAt 0 1 5  0 1 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n\
         Sampler \"halton\" \"integer pixelsamples\" 16\n\
         Film \"rgb\" \"string filename\" \"out.exr\"\n\
         WorldBegin\nMaterial \"diffuse\"\nShape \"plymesh\" \"string filename\" \"missing.ply\"\n",
    ));
    assert_has(&e, &["v4-scene.pbrt", "line 7", "missing.ply"]);
    // pbrt-v3 declarations that pbrt-v4 shares are not taken for pbrt-v4.
    let s = load(&common::write(
        &d,
        "v3.pbrt",
        &format!(
            "{head}WorldBegin\nAttributeBegin\nAreaLightSource \"diffuse\" \"rgb L\" [ 1 1 1 ]\n\
             Shape \"sphere\"\nAttributeEnd\nLightSource \"point\" \"rgb I\" [ 1 1 1 ]\n\
             \"rgb scale\" [ 2 2 2 ]\nWorldEnd\n"
        ),
    ));
    assert_eq!(s.lights.len(), 2);
}

#[test]
fn every_file_a_scene_reads_is_in_its_file_list() {
    let d = folder("files");
    write_plys(&d);
    write_obj(&d);
    write_png(&d);
    common::write(
        &d,
        "part.pbrt",
        "Shape \"plymesh\" \"string filename\" \"models/quad-bin.ply\"\n",
    );
    let p = common::write(
        &d,
        "scene.pbrt",
        r#"Camera "perspective"
WorldBegin
Texture "t" "spectrum" "imagemap" "string filename" "tex.png"
Material "matte" "texture Kd" "t"
Include "part.pbrt"
Shape "plymesh" "string filename" "quad.ply"
Shape "plymesh" "string filename" "./quad.ply"
WorldEnd
"#,
    );
    let canon = |n: &str| d.join(n).canonicalize().expect("canonical");
    let s = load(&p);
    assert_eq!(
        s.files,
        ["models/quad-bin.ply", "part.pbrt", "quad.ply", "tex.png"].map(canon)
    );
    let p = common::write(
        &d,
        "scene.xml",
        r#"<scene version="0.5.0">
  <sensor type="perspective"/>
  <bsdf type="diffuse" id="m">
    <texture type="bitmap" name="reflectance"><string name="filename" value="tex.png"/></texture>
  </bsdf>
  <shape type="obj"><string name="filename" value="quad.obj"/><ref id="m"/></shape>
  <shape type="ply"><string name="filename" value="models/quad-bin.ply"/></shape>
</scene>
"#,
    );
    let s = load(&p);
    assert_eq!(
        s.files,
        ["models/quad-bin.ply", "quad.obj", "tex.png"].map(canon)
    );
}
