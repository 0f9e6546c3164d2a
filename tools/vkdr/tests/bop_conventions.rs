//! BOP's camera convention as BOP means it: `cam_K` puts pixel centres on integer
//! coordinates (OpenCV), vkdr's camera puts pixel (i, j)'s centre at (j + 0.5, i + 0.5).
//! A frame written and read back has the same camera; a point that OpenCV projects onto a
//! pixel's centre lands on the same pixel's centre in vkdr.

use std::path::{Path, PathBuf};

use glam::DVec3;
use vkdr::{Camera, Pose};
use vkdr_app::bop::{self, Frame, FrameObject};

fn folder(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("bop_{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A 40 x 30 frame with one object whose mask is the left half, depth 0.8 m everywhere.
fn frame(camera: Camera) -> Frame {
    let n = (camera.width * camera.height) as usize;
    let visible = (0..n)
        .map(|i| ((i as u32 % camera.width) < camera.width / 2) as u32 as f32)
        .collect();
    Frame {
        scene: "000000".into(),
        image: 3,
        camera,
        depth: vec![0.8; n],
        rgb: None,
        objects: vec![FrameObject {
            gt_index: 0,
            obj_id: 7,
            model_to_camera: Pose::new([0.01, -0.02, 0.8], [0.1, 0.2, 0.3]).unwrap(),
            visible,
            whole: None,
        }],
    }
}

#[test]
fn a_written_frame_reads_back_with_the_same_camera() {
    let dir = folder("roundtrip");
    let camera = Camera::new(61.5, 62.25, 20.25, 14.75, 40, 30).unwrap();
    bop::write_frame(&dir, &frame(camera), 0.1).unwrap();
    // The file holds BOP's convention: the principal point half a pixel less.
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("scene_camera.json")).unwrap())
            .unwrap();
    let k: Vec<f64> = json["3"]["cam_K"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(k, [61.5, 0.0, 19.75, 0.0, 62.25, 14.25, 0.0, 0.0, 1.0]);
    let read = bop::read_scene(&dir).unwrap();
    assert_eq!(read.len(), 1);
    assert_eq!(read[0].camera, camera);
    let pose = read[0].objects[0].model_to_camera;
    let truth = frame(camera).objects[0].model_to_camera;
    assert!((pose.translation - truth.translation).length() < 1e-12);
    assert!((pose.rotation - truth.rotation).length() < 1e-9);
    assert_eq!(read[0].objects[0].visible, frame(camera).objects[0].visible);
}

#[test]
fn an_opencv_projection_lands_on_the_same_pixel() {
    let dir = folder("opencv");
    // A BOP camera file written by hand, as a converted dataset has it.
    let (fx, fy, cx, cy) = (500.0, 510.0, 19.0, 14.0);
    bop::write_frame(
        &dir,
        &frame(Camera::new(fx, fy, cx + 0.5, cy + 0.5, 40, 30).unwrap()),
        0.1,
    )
    .unwrap();
    let text = std::fs::read_to_string(dir.join("scene_camera.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json["3"]["cam_K"] = serde_json::json!([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]);
    std::fs::write(dir.join("scene_camera.json"), json.to_string()).unwrap();
    let camera = bop::read_scene(&dir).unwrap()[0].camera;
    // OpenCV: u = fx x / z + cx, and pixel column c's centre is u = c. A point projected
    // onto OpenCV's pixel (column 25, row 7) lies on that pixel's centre in vkdr's
    // convention too: (25.5, 7.5).
    let (column, row) = (25.0, 7.0);
    let z = 0.9;
    let p = DVec3::new((column - cx) * z / fx, (row - cy) * z / fy, z);
    let (u, v) = camera.project(p);
    assert!((u - (column + 0.5)).abs() < 1e-9, "u {u}");
    assert!((v - (row + 0.5)).abs() < 1e-9, "v {v}");
    assert_eq!((u.floor(), v.floor()), (column, row));
}
