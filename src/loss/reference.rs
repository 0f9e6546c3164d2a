//! Float64 references of the losses and of the signed distance field (exact, brute force).

use super::Loss;

/// Exact signed distance in pixels to a mask's boundary, with the device's convention:
/// outside, distance to the nearest mask pixel centre minus 1/2; inside, minus (distance
/// to the nearest background pixel centre minus 1/2); +-(width + height) without any pixel
/// of the other kind.
pub fn signed_distance(mask: &[f32], width: usize, height: usize) -> Vec<f64> {
    let pixels: Vec<(f64, f64, bool)> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x as f64, y as f64)))
        .zip(mask)
        .map(|((x, y), &m)| (x, y, m > 0.5))
        .collect();
    pixels
        .iter()
        .map(|&(x, y, inside)| {
            let nearest = pixels
                .iter()
                .filter(|p| p.2 != inside)
                .map(|p| ((p.0 - x).powi(2) + (p.1 - y).powi(2)).sqrt())
                .fold(f64::INFINITY, f64::min);
            let d = if nearest.is_finite() {
                nearest - 0.5
            } else {
                (width + height) as f64
            };
            if inside {
                -d
            } else {
                d
            }
        })
        .collect()
}

/// The loss of one view: `rendered` and `observed` hold `channels` values per pixel,
/// `distance` one (only for [`Loss::Distance`]).
pub fn loss(
    kind: Loss,
    rendered: &[f64],
    observed: &[f64],
    distance: &[f64],
    channels: usize,
) -> f64 {
    let n = (rendered.len() / channels) as f64;
    match kind {
        Loss::Mse => {
            rendered
                .iter()
                .zip(observed)
                .map(|(a, o)| (a - o).powi(2))
                .sum::<f64>()
                / (n * channels as f64)
        }
        Loss::Iou => {
            let intersection: f64 = rendered.iter().zip(observed).map(|(a, o)| a * o).sum();
            let union: f64 = rendered
                .iter()
                .zip(observed)
                .map(|(a, o)| a + o - a * o)
                .sum();
            if union > 0.0 {
                1.0 - intersection / union
            } else {
                0.0
            }
        }
        Loss::Distance => {
            rendered
                .iter()
                .zip(distance)
                .map(|(a, s)| a * s)
                .sum::<f64>()
                / n
        }
    }
}
