//! Supersampling's last step: averaging k x k blocks of a frame rendered k times larger.

use image::RgbaImage;

use super::Frame;

/// Averages `k` x `k` blocks of the color image (and keeps the nearest depth of each block).
pub fn downsample(frame: Frame, k: u32) -> Frame {
    let (width, height) = (frame.image.width() / k, frame.image.height() / k);
    let big_width = frame.image.width() as usize;
    let image = RgbaImage::from_fn(width, height, |x, y| {
        let mut sum = [0u32; 4];
        for dy in 0..k {
            for dx in 0..k {
                let p = frame.image.get_pixel(x * k + dx, y * k + dy).0;
                for c in 0..4 {
                    sum[c] += p[c] as u32;
                }
            }
        }
        let n = k * k;
        image::Rgba(sum.map(|s| ((s + n / 2) / n) as u8))
    });
    let depth = frame.depth.map(|depth| {
        let mut out = Vec::with_capacity((width * height) as usize);
        for y in 0..height as usize {
            for x in 0..width as usize {
                let mut nearest = f32::INFINITY;
                for dy in 0..k as usize {
                    for dx in 0..k as usize {
                        nearest = nearest
                            .min(depth[(y * k as usize + dy) * big_width + x * k as usize + dx]);
                    }
                }
                out.push(nearest);
            }
        }
        out
    });
    Frame {
        image,
        depth,
        ..frame
    }
}
