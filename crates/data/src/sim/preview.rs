//! Contact sheets for eyeballing the data: each sample's crop with projected LiDAR points, the 2D
//! labels and skeleton, next to a side view of its points with the 3D skeleton.

use image::{Rgb, RgbImage};

use posefuse_core::keypoints::SKELETON;
use posefuse_core::sample::Sample;

fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

fn dot(img: &mut RgbImage, x: f64, y: f64, r: i64, c: [u8; 3]) {
    let (cx, cy) = (x.floor() as i64, y.floor() as i64);
    for dy in -r..=r {
        for dx in -r..=r {
            if dx * dx + dy * dy <= r * r {
                put(img, cx + dx, cy + dy, c);
            }
        }
    }
}

fn line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], c: [u8; 3]) {
    let n = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).clamp(1, 4096);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        dot(img, a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, 1, c);
    }
}

fn depth_colour(z: f32) -> [u8; 3] {
    // Blue (low) to yellow (high) over the body's height.
    let t = ((z + 1.0) / 2.0).clamp(0.0, 1.0);
    [(255.0 * t) as u8, (200.0 * t + 55.0) as u8, (255.0 * (1.0 - t)) as u8]
}

fn kp_colour(k: usize) -> [u8; 3] {
    match k {
        0 => [255, 255, 255],
        k if k % 2 == 1 => [255, 60, 60],
        _ => [60, 255, 60],
    }
}

/// A contact sheet of up to `cols`×rows samples: crop | side view.
pub fn sheet(samples: &[&Sample], s: u32, cols: u32) -> RgbImage {
    let rows = (samples.len() as u32).div_ceil(cols).max(1);
    let mut img = RgbImage::from_pixel(cols * 2 * s, rows * s, Rgb([30, 30, 30]));
    for (n, smp) in samples.iter().enumerate() {
        let (ox, oy) = ((n as u32 % cols) * 2 * s, (n as u32 / cols) * s);
        let mut tile = RgbImage::from_raw(s, s, smp.image.clone()).unwrap_or_else(|| RgbImage::new(s, s));
        for (uv, xyz) in smp.points_uv.iter().zip(&smp.points_xyz) {
            if uv[0].is_finite() {
                dot(&mut tile, uv[0] as f64, uv[1] as f64, 0, depth_colour(xyz[2]));
            }
        }
        let kp = smp.kp2d.map(|p| [p[0] as f64, p[1] as f64]);
        for &(a, b) in &SKELETON {
            if smp.kp2d_visible[a] == 1 && smp.kp2d_visible[b] == 1 {
                line(&mut tile, kp[a], kp[b], [255, 200, 0]);
            }
        }
        for (k, p) in kp.iter().enumerate() {
            let c = if smp.kp2d_visible[k] == 1 { kp_colour(k) } else { [120, 120, 120] };
            dot(&mut tile, p[0], p[1], 2, c);
        }
        // Side view: local x (along the heading) to the right, z up; 2.4 m across the tile.
        let mut side = RgbImage::from_pixel(s, s, Rgb([12, 12, 20]));
        let px = s as f64 / 2.4;
        let to = |x: f32, z: f32| [s as f64 / 2.0 + x as f64 * px, s as f64 / 2.0 - z as f64 * px];
        for xyz in &smp.points_xyz {
            let p = to(xyz[0], xyz[2]);
            dot(&mut side, p[0], p[1], 1, [170, 170, 170]);
        }
        let k3: Vec<[f64; 2]> = smp.kp3d.iter().map(|q| to(q[0], q[2])).collect();
        for &(a, b) in &SKELETON {
            line(&mut side, k3[a], k3[b], [255, 200, 0]);
        }
        for (k, p) in k3.iter().enumerate() {
            dot(&mut side, p[0], p[1], 2, kp_colour(k));
        }
        image::imageops::replace(&mut img, &tile, ox as i64, oy as i64);
        image::imageops::replace(&mut img, &side, (ox + s) as i64, oy as i64);
    }
    img
}

/// A half-resolution view of a request fixture: the decoded image with the LiDAR points
/// projected (coloured by height) and the persons' 2D boxes and ground-truth skeletons.
pub fn frame_overview(frame: &posefuse_core::frame::Frame) -> posefuse_core::Result<RgbImage> {
    use base64::Engine;
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(frame.image.as_deref().unwrap_or_default())
        .map_err(|e| posefuse_core::Error::Io(format!("fixture image: {e}")))?;
    let full = posefuse_core::sample::decode_jpeg(&bytes)?;
    let calibration =
        frame.calibration.as_ref().ok_or_else(|| posefuse_core::Error::field("calibration", "required"))?;
    let cam = posefuse_core::geometry::Camera::from_calibration(calibration)?;
    let mut img =
        image::imageops::resize(&full, full.width() / 2, full.height() / 2, image::imageops::FilterType::Triangle);
    for p in frame.points.decode()? {
        let pr = cam.project([p[0] as f64, p[1] as f64, p[2] as f64]);
        if pr.in_image {
            dot(&mut img, pr.uv[0] / 2.0, pr.uv[1] / 2.0, 0, depth_colour(p[2] - 1.0));
        }
    }
    for person in &frame.persons {
        if let Some(b) = person.box_2d {
            let (x0, y0, x1, y1) = (
                (b.center_x - b.width / 2.0) / 2.0,
                (b.center_y - b.height / 2.0) / 2.0,
                (b.center_x + b.width / 2.0) / 2.0,
                (b.center_y + b.height / 2.0) / 2.0,
            );
            for (a, c) in [([x0, y0], [x1, y0]), ([x1, y0], [x1, y1]), ([x1, y1], [x0, y1]), ([x0, y1], [x0, y0])] {
                line(&mut img, a, c, [0, 255, 255]);
            }
        }
        if let Some(k2) = person.ground_truth.as_ref().and_then(|g| g.keypoints_2d.as_ref()) {
            for &(a, b) in &SKELETON {
                if k2.visible[a] && k2.visible[b] {
                    line(
                        &mut img,
                        [k2.uv[a][0] / 2.0, k2.uv[a][1] / 2.0],
                        [k2.uv[b][0] / 2.0, k2.uv[b][1] / 2.0],
                        [255, 200, 0],
                    );
                }
            }
        }
    }
    Ok(img)
}
