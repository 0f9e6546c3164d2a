//! Property tests of everything that reads user input: OBJ text, `.npy` headers and
//! arrays, `.npz` shape spaces, PNG masks and depth images, and the camera, pose and size
//! flags. Whatever the bytes or values, a parser returns an error or a valid result: no
//! panic, no abort, no allocation a header merely claims.

use std::path::PathBuf;

use proptest::prelude::*;
use vkdr::camera::{parse_numbers, parse_size};
use vkdr::{Camera, Mesh, Pose};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vkdr-parsers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// OBJ-like text: the statements vkdr reads, with numbers and indices of any kind.
fn obj_text() -> impl Strategy<Value = String> {
    let number = prop_oneof![
        any::<f64>().prop_map(|v| v.to_string()),
        Just("nan".to_string()),
        Just("1e39".to_string()),
        "[-0-9.e+]{0,8}",
    ];
    let index = prop_oneof![any::<i64>().prop_map(|v| v.to_string()), "[-0-9/]{0,6}",];
    let line = prop_oneof![
        (number.clone(), number.clone(), number).prop_map(|(a, b, c)| format!("v {a} {b} {c}")),
        prop::collection::vec(index, 0..6).prop_map(|i| format!("f {}", i.join(" "))),
        "[ -~]{0,20}",
    ];
    prop::collection::vec(line, 0..12).prop_map(|lines| lines.join("\n"))
}

fn npy_header(descr: &str, shape: &str) -> Vec<u8> {
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({shape}), }}");
    while (header.len() + 11) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    bytes
}

/// A size past isize::MAX beside a 0 declares no data, but no array can have that shape:
/// an error, not ndarray-npy's panic (found by the property test below).
#[test]
fn npy_with_a_size_past_isize_max_is_an_error() {
    for shape in [
        "0, 9223372036854775808",
        "9223372036854775808, 0",
        "0, 3, 4611686018427387904",
    ] {
        let bytes = npy_header("<f8", shape);
        let error = vkdr::io::points_from_npy("test.npy", &bytes).unwrap_err();
        assert!(
            error.to_string().contains("larger than any array"),
            "{error}"
        );
    }
}

/// An element type of size 0 (`<x0`, no numpy type) declares no data for any shape, and
/// ndarray-npy allocates the whole shape before it looks at the type: the size is checked
/// as if each element held a byte (found by the property test below, which aborted the
/// process allocating 7.4e18 bytes).
#[test]
fn npy_with_an_element_of_size_0_is_an_error() {
    for descr in ["<x0", "|b0", ">f00"] {
        let bytes = npy_header(descr, "1850029010375106144,");
        let error = vkdr::io::points_from_npy("test.npy", &bytes).unwrap_err();
        assert!(error.to_string().contains("but the file holds"), "{error}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn obj_text_is_a_mesh_or_an_error(text in obj_text()) {
        if let Ok(mesh) = Mesh::parse_obj(&text) {
            let n = mesh.vertex_count();
            prop_assert!(mesh.triangles().iter().flatten().all(|&i| (i as usize) < n));
            prop_assert!(mesh.positions().iter().flatten().all(|c| c.is_finite()));
        }
    }

    #[test]
    fn arbitrary_bytes_as_obj_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
        let _ = Mesh::parse_obj(&String::from_utf8_lossy(&bytes));
    }

    #[test]
    fn npy_points_with_any_header_are_points_or_an_error(
        descr in prop_oneof![
            Just("<f8".to_string()),
            Just("<f4".to_string()),
            Just("<i4".to_string()),
            Just("|u1".to_string()),
            "[<>|][a-z][0-9]{1,2}",
        ],
        dims in prop::collection::vec(prop_oneof![0u64..5, Just(3u64), any::<u64>()], 0..4),
        data in prop::collection::vec(any::<u8>(), 0..256),
    ) {
        let shape = dims.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ");
        let mut bytes = npy_header(&descr, &shape);
        bytes.extend(&data);
        if let Ok(points) = vkdr::io::points_from_npy("test.npy", &bytes) {
            prop_assert_eq!(dims.len(), 2);
            prop_assert_eq!(points.len() as u64, dims[0]);
        }
    }

    #[test]
    fn npy_bytes_of_any_kind_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        let _ = vkdr::io::check_npy_size("test.npy", &bytes);
        let _ = vkdr::io::points_from_npy("test.npy", &bytes);
        let mut magic = b"\x93NUMPY".to_vec();
        magic.extend(&bytes);
        let _ = vkdr::io::points_from_npy("test.npy", &magic);
    }

    #[test]
    fn numbers_flags_parse_or_err(text in "[-0-9.,eEinfaNx ]{0,40}") {
        if let Ok(values) = parse_numbers::<4>(&text, "--intrinsics") {
            prop_assert_eq!(values.len(), 4);
        }
        if let Ok((w, h)) = parse_size(&text) {
            prop_assert!(w > 0 && h > 0);
        }
    }

    #[test]
    fn cameras_and_poses_from_any_values_are_valid_or_an_error(
        v in prop::array::uniform6(prop_oneof![any::<f64>(), -1e3f64..1e3]),
        w in 0u32..5000,
        h in 0u32..5000,
        near in any::<f64>(),
    ) {
        if let Ok(camera) = Camera::new(v[0], v[1], v[2], v[3], w, h) {
            prop_assert!(camera.fx > 0.0 && camera.fx.is_finite() && camera.width > 0);
            let with_near = Camera { near, ..camera }.validated();
            if let Ok(c) = with_near {
                prop_assert!(c.near > 0.0 && c.near.is_finite());
            }
        }
        if let Ok(pose) = Pose::new([v[0], v[1], v[2]], [v[3], v[4], v[5]]) {
            let m = pose.rotation_matrix();
            prop_assert!(m.to_cols_array().iter().all(|x| x.is_finite()));
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// PNG bytes, valid or corrupted at any byte, as a mask or a depth image.
    #[test]
    fn png_masks_and_depth_images_read_or_err(
        w in 1u32..6,
        h in 1u32..6,
        pixels in prop::collection::vec(any::<u16>(), 36 * 4),
        kind in 0usize..4,
        flip in prop::option::of((any::<prop::sample::Index>(), any::<u8>())),
    ) {
        let at = |x: u32, y: u32, c: usize| pixels[((y * w + x) as usize) * 4 + c];
        let image: image::DynamicImage = match kind {
            0 => image::GrayImage::from_fn(w, h, |x, y| image::Luma([at(x, y, 0) as u8])).into(),
            1 => image::ImageBuffer::<image::Luma<u16>, _>::from_fn(w, h, |x, y| image::Luma([at(x, y, 0)])).into(),
            2 => image::RgbImage::from_fn(w, h, |x, y| image::Rgb([0, 1, 2].map(|c| at(x, y, c) as u8))).into(),
            _ => image::RgbaImage::from_fn(w, h, |x, y| image::Rgba([0, 1, 2, 3].map(|c| at(x, y, c) as u8))).into(),
        };
        let mut bytes = Vec::new();
        image.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png).unwrap();
        if let Some((index, value)) = flip {
            let i = index.index(bytes.len());
            bytes[i] = value;
        }
        let path = scratch(&format!("mask-{kind}-{w}x{h}.png"));
        std::fs::write(&path, &bytes).unwrap();
        if let Ok(mask) = vkdr::loss::load_mask(&path, w, h) {
            prop_assert_eq!(mask.len(), (w * h) as usize);
            prop_assert!(mask.iter().all(|&m| m == 0.0 || m == 1.0));
        }
        if let Ok(depth) = vkdr::loss::load_depth(&path, w, h, 1.0) {
            prop_assert_eq!(kind, 1);
            prop_assert!(depth.iter().all(|&z| z >= 0.0 && z.is_finite()));
        }
        // The wrong size is always an error.
        prop_assert!(vkdr::loss::load_mask(&path, w + 1, h).is_err());
    }

    /// A shape space file with any byte changed: loaded whole or refused.
    #[test]
    fn a_corrupted_shape_space_loads_or_errs(
        index in any::<prop::sample::Index>(),
        value in any::<u8>(),
    ) {
        let original = shape_space_file();
        let mut bytes = std::fs::read(&original).unwrap();
        let i = index.index(bytes.len());
        bytes[i] = value;
        let path = scratch(&format!("space-{i}-{value}.npz"));
        std::fs::write(&path, &bytes).unwrap();
        std::fs::copy(
            original.with_extension("npz.json"),
            path.with_extension("npz.json"),
        )
        .unwrap();
        if let Ok(space) = vkdr::shape::ShapeSpace::load(&path) {
            prop_assert_eq!(space.deformation_basis.len(), space.dims());
            prop_assert!(space.vertices(&vec![0.0; space.dims()]).is_ok());
        }
        std::fs::remove_file(&path).unwrap();
        std::fs::remove_file(path.with_extension("npz.json")).unwrap();
    }
}

/// A shape space whose array header claims far more data than the file holds (a shape of
/// 1e14 rows: allocating for it aborted the process) is refused before anything is read.
#[test]
fn a_shape_space_header_claiming_too_much_is_refused() {
    let original = shape_space_file();
    let mut bytes = std::fs::read(&original).unwrap();
    let find = |from: usize, what: &[u8]| {
        from + bytes[from..]
            .windows(what.len())
            .position(|w| w == what)
            .unwrap()
    };
    // The first array's shape "a, b), }" grows into the header's padding: same length.
    let at = find(0, b"'shape': (") + "'shape': (".len();
    let end = find(at, b"}") + 1;
    let padding = find(end, b"\n") - end;
    let grown = [b"100000000000000", &bytes[at..end]].concat();
    assert!(
        grown.len() <= end - at + padding,
        "no room in the header's padding"
    );
    bytes[at..at + grown.len()].copy_from_slice(&grown);
    let path = scratch("lying-space.npz");
    std::fs::write(&path, &bytes).unwrap();
    std::fs::copy(
        original.with_extension("npz.json"),
        path.with_extension("npz.json"),
    )
    .unwrap();
    let error = vkdr::shape::ShapeSpace::load(&path).expect_err("refused");
    assert!(error.to_string().contains("declares shape"), "{error}");
}

/// A small shape space saved once (from fits made on the host: no device needed).
fn shape_space_file() -> PathBuf {
    static ONCE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ONCE.get_or_init(|| {
        let canonical = Mesh::uv_sphere(0.1, 4, 6);
        let m = canonical.vertex_count();
        let fits: Vec<vkdr::shape::TrainingFit> = (0..3)
            .map(|i| {
                let w: Vec<f64> = (0..3 * m)
                    .map(|k| ((k * 7 + i * 13) % 11) as f64 * 1e-3)
                    .collect();
                vkdr::shape::TrainingFit {
                    displacement: w.iter().map(|x| 0.5 * x).collect(),
                    w,
                }
            })
            .collect();
        let names = (0..3).map(|i| format!("t{i}")).collect();
        let space =
            vkdr::shape::ShapeSpace::from_fits("sphere", &canonical, 2.0, &fits, 2, names).unwrap();
        let path = scratch("space.npz");
        space.save(&path).unwrap();
        path
    })
    .clone()
}

/// A PLY of two triangles and a quad over five vertices, with normals and colours besides
/// the positions and an element after the faces, as BOP's models have: its header (format
/// line given) and body.
fn ply_header(format: &str) -> String {
    format!(
        "ply\nformat {format} 1.0\ncomment made by the tests\nelement vertex 5\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face 3\nproperty list uchar int vertex_indices\n\
         element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n"
    )
}

const PLY_POSITIONS: [[f32; 3]; 5] = [
    [0.0, 0.0, 0.0],
    [10.0, 0.0, 0.0],
    [0.0, 10.0, 0.0],
    [0.0, 0.0, 10.5],
    [-3.25, 2.0, 1.0],
];
const PLY_FACES: [&[u32]; 3] = [&[0, 2, 1], &[0, 1, 3], &[1, 2, 3, 4]];

fn ply_ascii() -> Vec<u8> {
    let mut text = ply_header("ascii");
    for p in PLY_POSITIONS {
        text += &format!("{} {} {} 0 0 1 255 128 0\n", p[0], p[1], p[2]);
    }
    for f in PLY_FACES {
        text += &format!(
            "{} {}\n",
            f.len(),
            f.iter()
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    text += "0 1\n";
    text.into_bytes()
}

fn ply_binary() -> Vec<u8> {
    let mut bytes = ply_header("binary_little_endian").into_bytes();
    for p in PLY_POSITIONS {
        for c in p.iter().chain(&[0.0, 0.0, 1.0]) {
            bytes.extend(c.to_le_bytes());
        }
        bytes.extend([255u8, 128, 0]);
    }
    for f in PLY_FACES {
        bytes.push(f.len() as u8);
        for i in f {
            bytes.extend((*i as i32).to_le_bytes());
        }
    }
    bytes.extend(0i32.to_le_bytes());
    bytes.extend(1i32.to_le_bytes());
    bytes
}

#[test]
fn ply_ascii_and_binary_read_the_same_mesh() {
    let want = Mesh::new(
        PLY_POSITIONS.to_vec(),
        vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [1, 3, 4]],
    )
    .unwrap();
    for (name, bytes) in [("ascii.ply", ply_ascii()), ("binary.ply", ply_binary())] {
        let path = scratch(name);
        std::fs::write(&path, bytes).unwrap();
        assert_eq!(Mesh::load_ply(&path).unwrap(), want, "{name}");
        assert_eq!(Mesh::load(&path).unwrap(), want, "{name} by its extension");
    }
}

#[test]
fn bad_ply_is_an_error_naming_the_problem() {
    let binary = ply_binary();
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "endian.ply",
            String::from_utf8(ply_ascii()).unwrap().replace("format ascii", "format binary_big_endian").into_bytes(),
            "format 'binary_big_endian' is not read",
        ),
        ("cut.ply", binary[..binary.len() - 30].to_vec(), "the data end before the header's counts"),
        (
            "points.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n".to_vec(),
            "no face element",
        ),
        (
            "range.ply",
            String::from_utf8(ply_ascii()).unwrap().replace("4 1 2 3 4", "4 1 2 3 9").into_bytes(),
            "refers to a vertex out of range",
        ),
        ("text.ply", b"solid cube\nfacet normal 0 0 1\n".to_vec(), "no 'end_header'"),
        (
            "nan.ply",
            String::from_utf8(ply_ascii()).unwrap().replace("10.5", "nan").into_bytes(),
            "not finite",
        ),
    ];
    for (name, bytes, says) in cases {
        let path = scratch(name);
        std::fs::write(&path, bytes).unwrap();
        let err = Mesh::load_ply(&path).unwrap_err().to_string();
        assert!(err.contains(says) && err.contains(name), "{name}: {err}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// Any bytes after a valid header, or any header, are a mesh or an error: never a
    /// panic, never an allocation the file does not back.
    #[test]
    fn ply_from_any_bytes_is_a_mesh_or_an_error(
        body in proptest::collection::vec(any::<u8>(), 0..400),
        cut in 0usize..600,
    ) {
        let mut bytes = ply_header("binary_little_endian").into_bytes();
        bytes.extend(&body);
        let path = scratch("any.ply");
        std::fs::write(&path, &bytes).unwrap();
        let _ = Mesh::load_ply(&path);
        let mut ascii = ply_ascii();
        ascii.truncate(cut.min(ascii.len()));
        std::fs::write(&path, &ascii).unwrap();
        let _ = Mesh::load_ply(&path);
    }
}
