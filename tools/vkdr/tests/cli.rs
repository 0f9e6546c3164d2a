//! Bad input at the command line, as a careless or hostile user gives it: every case must
//! exit non-zero with a message that names the problem, and leave what was already in
//! `--out` untouched (the cases run with `--force` where they pass the claim on `--out`,
//! so that the bad input itself is what stops them).

use std::path::{Path, PathBuf};
use std::process::Command;

/// The fixture folder: small inputs, good and bad, and a generated dataset.
fn fixtures() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let write = |name: &str, bytes: &[u8]| std::fs::write(dir.join(name), bytes).unwrap();
    write("tri.obj", b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n");
    write("huge.obj", b"v 1e30 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n");
    write("cut.obj", b"v 0 0\nf 1 2 3\n");
    write("face.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
    let npy = |rows: &[[f64; 3]]| {
        let array = ndarray::Array2::from_shape_fn((rows.len(), 3), |(i, j)| rows[i][j]);
        let mut bytes = Vec::new();
        ndarray_npy::WriteNpyExt::write_npy(&array, &mut bytes).unwrap();
        bytes
    };
    let points: Vec<[f64; 3]> = (0..40)
        .map(|i| {
            let t = i as f64 * 0.3;
            [t.cos(), t.sin(), 0.1 * t]
        })
        .collect();
    write("points.npy", &npy(&points));
    write("same.npy", &npy(&[[0.1, 0.2, 0.3]; 20]));
    let mut nan = points.clone();
    nan[7][1] = f64::NAN;
    write("nan.npy", &npy(&nan));
    // A 200-byte file whose header claims 1e12 x 3 floats.
    let mut huge = b"\x93NUMPY\x01\x00".to_vec();
    let header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000000, 3), }\n";
    huge.extend((header.len() as u16).to_le_bytes());
    huge.extend(header);
    huge.resize(200, 0);
    write("claims.npy", &huge);
    image::GrayImage::new(20, 10)
        .save(dir.join("mask20x10.png"))
        .unwrap();
    image::GrayImage::from_pixel(64, 48, image::Luma([255]))
        .save(dir.join("mask64x48.png"))
        .unwrap();
    let depth = ndarray::Array2::from_elem((48, 64), -0.5f32);
    let mut bytes = Vec::new();
    ndarray_npy::WriteNpyExt::write_npy(&depth, &mut bytes).unwrap();
    write("negative_depth.npy", &bytes);
    write("views.json", b"{\"views\": [");
    write("corrupt.npz", b"PK\x03\x04 not a zip");
    write("corrupt.npz.json", b"{\"format_version\": 1}");
    std::fs::create_dir_all(dir.join("no_categories/stuff")).unwrap();
    vkdr(
        &["gen-dataset", "--out", dir.join("data").to_str().unwrap()],
        &dir,
    );
    // A category whose test/ is empty.
    let empty = dir.join("empty_tests/bottle");
    std::fs::create_dir_all(empty.join("test")).unwrap();
    std::fs::create_dir_all(empty.join("train")).unwrap();
    for name in ["canonical.obj", "info.json"] {
        std::fs::copy(dir.join("data/bottle").join(name), empty.join(name)).unwrap();
    }
    for entry in std::fs::read_dir(dir.join("data/bottle/train")).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, empty.join("train").join(path.file_name().unwrap())).unwrap();
    }
    vkdr(
        &[
            "shape-space",
            dir.join("data/bottle").to_str().unwrap(),
            "--out",
            dir.join("space.npz").to_str().unwrap(),
        ],
        &dir,
    );
    write("existing_file", b"precious");
    dir
}

/// Runs vkdr in `dir`; panics unless it succeeds.
fn vkdr(args: &[&str], dir: &Path) {
    let out = Command::new(env!("CARGO_BIN_EXE_vkdr"))
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "vkdr {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

const CAMERA: &[&str] = &["--intrinsics", "80,80,32,24", "--size", "64x48"];
const POSE: &[&str] = &["--pose", "0,0,0.5,0,0,0"];

/// One bad case: its arguments (`OUT` stands for a folder that already holds a file, and
/// `--force` is added where the case is not about the claim), what the message must say,
/// and environment variables.
struct Case {
    args: Vec<&'static str>,
    says: &'static str,
    env: Option<(&'static str, &'static str)>,
}

fn case(args: &[&'static str], says: &'static str) -> Case {
    Case {
        args: args.to_vec(),
        says,
        env: None,
    }
}

fn with(parts: &[&[&'static str]]) -> Vec<&'static str> {
    parts.concat()
}

#[test]
fn bad_input_exits_non_zero_naming_the_problem_and_keeps_existing_files() {
    let dir = fixtures();
    let render = |extra: &[&'static str], mesh: &'static str| {
        with(&[&["render", mesh], extra, &["--out", "OUT"]])
    };
    let register = |extra: &[&'static str]| {
        with(&[
            &[
                "register",
                "--space",
                "space.npz",
                "--observed-mesh",
                "data/bottle/test/bottle_test_00.obj",
            ],
            CAMERA,
            POSE,
            extra,
            &["--out", "OUT"],
        ])
    };
    let eval = |extra: &[&'static str]| {
        with(&[
            &["eval", "--dataset", "data", "--categories", "bottle"],
            extra,
            &["--out", "OUT"],
        ])
    };
    let cases = vec![
        // Meshes.
        case(&render(&[CAMERA, POSE].concat(), "huge.obj"), "past 1e6 m"),
        case(
            &render(&[CAMERA, POSE].concat(), "missing.obj"),
            "missing.obj",
        ),
        case(&render(&[CAMERA, POSE].concat(), "cut.obj"), "line 1"),
        case(
            &render(&[CAMERA, POSE].concat(), "face.obj"),
            "out of range",
        ),
        // Camera, pose and size flags.
        case(
            &render(
                &with(&[&["--intrinsics", "1e300,80,32,24", "--size", "64x48"], POSE]),
                "tri.obj",
            ),
            "fx=1e300",
        ),
        case(
            &render(
                &with(&[CAMERA, &["--pose", "0,0,0.5,1e300,0,0"]]),
                "tri.obj",
            ),
            "rotation",
        ),
        case(
            &render(&with(&[CAMERA, &["--pose", "0,0,nan,0,0,0"]]), "tri.obj"),
            "non-finite",
        ),
        case(
            &render(&with(&[CAMERA, POSE, &["--near", "nan"]]), "tri.obj"),
            "near plane",
        ),
        case(
            &render(
                &with(&[&["--intrinsics", "80,80,32,24", "--size", "0x48"], POSE]),
                "tri.obj",
            ),
            "size",
        ),
        case(
            &render(
                &with(&[&["--intrinsics", "80,80,32", "--size", "64x48"], POSE]),
                "tri.obj",
            ),
            "--intrinsics",
        ),
        // grad.
        case(
            &with(&[
                &["grad", "tri.obj", "--observed", "mask20x10.png"],
                CAMERA,
                POSE,
                &["--loss", "mse", "--out", "OUT"],
            ]),
            "--size is 64x48",
        ),
        case(
            &with(&[
                &["grad", "tri.obj", "--observed", "mask20x10.png"],
                CAMERA,
                POSE,
                &["--loss", "l7", "--out", "OUT"],
            ]),
            "invalid value 'l7' for '--loss <LOSS>'\n  [possible values: mse, iou, distance]",
        ),
        // cpd.
        case(
            &[
                "cpd",
                "points.npy",
                "points.npy",
                "--lambda",
                "1e-300",
                "--out",
                "OUT",
            ],
            "lambda 1e-300",
        ),
        case(
            &[
                "cpd",
                "points.npy",
                "points.npy",
                "--w",
                "1.5",
                "--out",
                "OUT",
            ],
            "w 1.5",
        ),
        case(
            &[
                "cpd",
                "points.npy",
                "points.npy",
                "--beta",
                "-2",
                "--out",
                "OUT",
            ],
            "beta -2",
        ),
        case(
            &["cpd", "same.npy", "points.npy", "--out", "OUT"],
            "all the same point",
        ),
        case(
            &["cpd", "claims.npy", "points.npy", "--out", "OUT"],
            "declares shape (1000000000000, 3)",
        ),
        case(
            &["cpd", "points.npy", "nan.npy", "--out", "OUT"],
            "not finite",
        ),
        // Where outputs go: never over what is there.
        case(
            &["cpd", "points.npy", "points.npy", "--out", "existing_file"],
            "not a folder",
        ),
        case(
            &["cpd", "points.npy", "points.npy", "--out", "/dev/null"],
            "not a folder",
        ),
        case(
            &["cpd", "points.npy", "points.npy", "--out", "NOFORCE"],
            "already holds",
        ),
        case(&["gen-dataset", "--out", "NOFORCE"], "--force"),
        case(
            &["shape-space", "data/bottle", "--out", "existing_file"],
            "existing_file exists",
        ),
        // eval.
        case(
            &[
                "eval",
                "--dataset",
                "data",
                "--categories",
                "botle",
                "--out",
                "OUT",
            ],
            "no category \"botle\"",
        ),
        case(&eval(&["--latent-step", "-1"]), "latent step -1"),
        case(
            &eval(&["--translation-step", "nan"]),
            "translation step NaN",
        ),
        case(&eval(&["--trials", "1"]), "--trials"),
        case(&eval(&["--views", "7"]), "--views"),
        case(&eval(&["--starts", "0"]), "--starts"),
        case(&eval(&["--depth", "--depth-noise", "-1"]), "--depth-noise"),
        case(&eval(&["--dims", "0"]), "--dims"),
        case(&eval(&["--code-prior", "-1"]), "--code-prior must be auto or a weight in [0, 1], not -1"),
        case(
            &eval(&["--depth", "--depth-scale", "0.01"]),
            "the depth cost's scale is --depth-sigma",
        ),
        case(
            &eval(&["--gravity", "known", "--tilt-tolerance", "95"]),
            "--tilt-tolerance must be 0 to 90 degrees, not 95",
        ),
        case(
            &[
                "eval-frames",
                "data",
                "--categories",
                "map.json",
                "--tilt-tolerance",
                "-5",
                "--out",
                "OUT",
            ],
            "--tilt-tolerance must be 0 to 90 degrees, not -5",
        ),
        case(
            &eval(&["--tilt-tolerance", "2"]),
            "--tilt-tolerance is the tolerance of --gravity: give --gravity too",
        ),
        case(
            &[
                "eval-frames",
                "data",
                "--gravity",
                "none",
                "--tilt-tolerance",
                "2",
                "--out",
                "OUT",
            ],
            "--tilt-tolerance is the tolerance of --gravity",
        ),
        case(
            &["eval-frames", "data", "--min-visible", "-0.5", "--out", "OUT"],
            "--min-visible must be 0 to 1, not -0.5",
        ),
        case(
            &["eval-frames", "data", "--depth-detail", "4", "--out", "OUT"],
            "depth detail 4 must be 0 (every pixel) or at least 8 samples",
        ),
        case(
            &["eval-frames", "data", "--depth-detail", "-1", "--out", "OUT"],
            "invalid value '-1' for '--depth-detail",
        ),
        case(
            &["eval", "--dataset", "empty_tests", "--out", "OUT"],
            "no meshes",
        ),
        case(
            &["eval", "--dataset", "no_categories", "--out", "OUT"],
            "no category folders",
        ),
        // shape-space.
        case(
            &[
                "shape-space",
                "data/bottle",
                "--dims",
                "0",
                "--out",
                "OUT/space.npz",
            ],
            "--dims",
        ),
        case(
            &[
                "shape-space",
                "data/bottle",
                "--lambda",
                "0",
                "--out",
                "OUT/space.npz",
            ],
            "lambda 0",
        ),
        // register.
        case(
            &[
                "register",
                "--space",
                "corrupt.npz",
                "--observed-mesh",
                "tri.obj",
                "--intrinsics",
                "80,80,32,24",
                "--size",
                "64x48",
                "--pose",
                "0,0,0.5,0,0,0",
                "--out",
                "OUT",
            ],
            "corrupt.npz",
        ),
        case(
            &with(&[
                &[
                    "register",
                    "--space",
                    "space.npz",
                    "--observed",
                    "mask20x10.png",
                    "--observed-depth",
                    "negative_depth.npy",
                ],
                &["--intrinsics", "80,80,10,5", "--size", "20x10"],
                POSE,
                &["--out", "OUT"],
            ]),
            "depth is (48, 64) (rows, columns) but --size is 20x10",
        ),
        case(
            &with(&[
                &[
                    "register",
                    "--space",
                    "space.npz",
                    "--observed",
                    "mask64x48.png",
                    "--observed-depth",
                    "negative_depth.npy",
                ],
                CAMERA,
                POSE,
                &["--out", "OUT"],
            ]),
            "depth at row 0 column 0 is -0.5",
        ),
        case(
            &register(&["--views", "views.json"]),
            "views.json: not JSON",
        ),
        case(&register(&["--starts", "3"]), "give --optimize-pose too"),
        case(
            &register(&["--optimize-pose", "--starts", "2", "--up", "0,0,0"]),
            "--up must be a nonzero direction",
        ),
        case(
            &register(&["--depth", "--depth-sigma", "0"]),
            "--depth-sigma, --depth-weight or --occlusion: invalid input: the depth loss scale",
        ),
        case(
            &register(&["--depth", "--occlusion", "-0.01"]),
            "occlusion tolerance must be >= 0 m",
        ),
        case(
            &with(&[
                &[
                    "register",
                    "--space",
                    "space.npz",
                    "--observed",
                    "mask64x48.png",
                    "--observed-depth",
                    "negative_depth.npy",
                    "--depth-scale",
                    "0.1",
                ],
                CAMERA,
                POSE,
                &["--out", "OUT"],
            ]),
            "does not apply to negative_depth.npy, which holds metres",
        ),
        case(
            &with(&[
                &[
                    "register",
                    "--space",
                    "space.npz",
                    "--observed",
                    "mask64x48.png",
                    "--ignore",
                    "mask20x10.png",
                ],
                CAMERA,
                POSE,
                &["--out", "OUT"],
            ]),
            "mask20x10.png: mask is 20x10 but --size is 64x48",
        ),
        case(&register(&["--iterations", "1000000"]), "at most 100000"),
        case(
            &register(&["--optimizer", "newton"]),
            "invalid value 'newton' for '--optimizer <OPTIMIZER>'\n  [possible values: sgd, adam, bfgs]",
        ),
        // Device limits and the environment.
        case(
            &["bench", "--size", "100000", "--out", "OUT"],
            "maxStorageBufferRange",
        ),
        case(
            &["bench-register", "--subdivide", "12", "--out", "OUT"],
            "--subdivide 12",
        ),
        Case {
            args: vec!["info"],
            says: "VKDR_FENCE_TIMEOUT_S='nan'",
            env: Some(("VKDR_FENCE_TIMEOUT_S", "nan")),
        },
    ];
    assert!(cases.len() >= 30);
    let mut failures = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        // Each case its own output folder, already holding a file that must survive.
        let out = dir.join(format!("out_{i}"));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("keep.txt"), b"precious").unwrap();
        let mut args: Vec<String> = Vec::new();
        let mut force = false;
        for a in &case.args {
            args.push(match *a {
                "OUT" => {
                    force = true;
                    out.to_str().unwrap().to_string()
                }
                "NOFORCE" => out.to_str().unwrap().to_string(),
                a if a.starts_with("OUT/") => {
                    force = true;
                    out.join(&a[4..]).to_str().unwrap().to_string()
                }
                a => a.to_string(),
            });
        }
        if force {
            args.push("--force".into());
        }
        let mut command = Command::new(env!("CARGO_BIN_EXE_vkdr"));
        command.args(&args).current_dir(&dir);
        if let Some((key, value)) = case.env {
            command.env(key, value);
        }
        let result = command.output().unwrap();
        let said = String::from_utf8_lossy(&result.stderr).into_owned()
            + &String::from_utf8_lossy(&result.stdout);
        let code = result.status.code();
        let kept = std::fs::read(out.join("keep.txt")).ok() == Some(b"precious".to_vec())
            && std::fs::read(dir.join("existing_file")).ok() == Some(b"precious".to_vec());
        let stderr = String::from_utf8_lossy(&result.stderr);
        let last = stderr.lines().last().unwrap_or("").to_string();
        // `cargo test --test cli -- --nocapture` lists every case with what it says.
        eprintln!("{:>2}. vkdr {}\n    -> {last}", i + 1, case.args.join(" "));
        if !(matches!(code, Some(c) if c != 0) && said.contains(case.says) && kept) {
            failures.push(format!(
                "vkdr {}: exit {code:?}, kept {kept}, expected '{}' in: {last}",
                args.join(" "),
                case.says
            ));
        }
        // A panic, an abort or a signal is never an answer.
        assert!(
            !said.contains("panicked") && code.is_some_and(|c| c == 1 || c == 2),
            "vkdr {}: {said}",
            args.join(" ")
        );
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
