//! An RGBA image to draw the overlay into: alpha-blended points, lines, discs, rectangles and
//! 8×8 bitmap text (`font8x8`'s public-domain glyphs). Everything clips to the image, so callers
//! may draw with any coordinates, even ones far off-screen.

/// Straight (not premultiplied) RGBA8.
pub type Rgba = [u8; 4];

pub const SHADOW: Rgba = [0, 0, 0, 170];

pub struct Canvas {
    pub width: u32,
    pub height: u32,
    /// Row-major, top row first.
    pub pixels: Vec<Rgba>,
}

impl Canvas {
    pub fn new(width: u32, height: u32) -> Canvas {
        Canvas {
            width,
            height,
            pixels: vec![[0; 4]; width as usize * height as usize],
        }
    }

    /// Fully transparent again (and resized).
    pub fn clear(&mut self, width: u32, height: u32) {
        self.width = width;
        self.height = height;
        self.pixels.clear();
        self.pixels.resize(width as usize * height as usize, [0; 4]);
    }

    pub fn get(&self, x: u32, y: u32) -> Rgba {
        self.pixels[(y * self.width + x) as usize]
    }

    /// Blends `c` over the pixel at `(x, y)` ("over" in straight alpha).
    pub fn blend(&mut self, x: i32, y: i32, c: Rgba) {
        if x < 0 || y < 0 || x >= self.width as i32 || y >= self.height as i32 || c[3] == 0 {
            return;
        }
        let p = &mut self.pixels[(y as u32 * self.width + x as u32) as usize];
        let a = u32::from(c[3]);
        let b = u32::from(p[3]);
        let out_a = a * 255 + b * (255 - a);
        if out_a == 0 {
            return;
        }
        for i in 0..3 {
            let v = (u32::from(c[i]) * a * 255 + u32::from(p[i]) * b * (255 - a)) / out_a;
            p[i] = v.min(255) as u8;
        }
        p[3] = (out_a / 255).min(255) as u8;
    }

    pub fn rect(&mut self, x: i32, y: i32, w: i32, h: i32, c: Rgba) {
        let (x0, y0) = (x.max(0), y.max(0));
        let (x1, y1) = (
            x.saturating_add(w).min(self.width as i32),
            y.saturating_add(h).min(self.height as i32),
        );
        for yy in y0..y1 {
            for xx in x0..x1 {
                self.blend(xx, yy, c);
            }
        }
    }

    /// A filled disc centred on `(cx, cy)`.
    pub fn disc(&mut self, cx: f32, cy: f32, r: f32, c: Rgba) {
        if !(cx.is_finite() && cy.is_finite() && r.is_finite()) {
            return;
        }
        let (x0, x1) = ((cx - r).floor() as i32, (cx + r).ceil() as i32);
        let (y0, y1) = ((cy - r).floor() as i32, (cy + r).ceil() as i32);
        for y in y0.max(-1)..=y1.min(self.height as i32) {
            for x in x0.max(-1)..=x1.min(self.width as i32) {
                let (dx, dy) = (x as f32 + 0.5 - cx, y as f32 + 0.5 - cy);
                if dx * dx + dy * dy <= r * r {
                    self.blend(x, y, c);
                }
            }
        }
    }

    /// A line `width` pixels wide, clipped to the image.
    pub fn line(&mut self, a: (f32, f32), b: (f32, f32), width: f32, c: Rgba) {
        let Some((a, b)) = clip(a, b, self.width as f32, self.height as f32) else {
            return;
        };
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let steps = dx.abs().max(dy.abs()).ceil().max(1.0) as i32;
        let half = (width * 0.5).max(0.5);
        let reach = half.ceil() as i32 - 1;
        let mut last = (i32::MIN, i32::MIN);
        for i in 0..=steps {
            let t = i as f32 / steps as f32;
            let (x, y) = ((a.0 + dx * t).floor() as i32, (a.1 + dy * t).floor() as i32);
            if (x, y) == last {
                continue;
            }
            last = (x, y);
            for oy in -reach..=reach {
                for ox in -reach..=reach {
                    self.blend(x + ox, y + oy, c);
                }
            }
        }
    }

    /// Text with its top-left corner at `(x, y)`, each 8×8 glyph scaled by `scale`; characters
    /// outside ASCII show as `?`. Returns the width drawn.
    pub fn text(&mut self, x: i32, y: i32, text: &str, scale: i32, c: Rgba) -> i32 {
        let mut pen = x;
        for ch in text.chars() {
            let code = if ch.is_ascii() && !ch.is_ascii_control() {
                ch as usize
            } else {
                '?' as usize
            };
            let glyph = font8x8::legacy::BASIC_LEGACY[code];
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..8 {
                    if bits >> col & 1 == 1 {
                        let (px, py) = (pen + col * scale, y + row as i32 * scale);
                        for sy in 0..scale {
                            for sx in 0..scale {
                                self.blend(px + sx, py + sy, c);
                            }
                        }
                    }
                }
            }
            pen += 8 * scale;
        }
        pen - x
    }

    /// Text with a one-pixel dark shadow, readable on any background.
    pub fn label(&mut self, x: i32, y: i32, text: &str, c: Rgba) -> i32 {
        self.text(x + 1, y + 1, text, 1, SHADOW);
        self.text(x, y, text, 1, c)
    }
}

/// Cohen–Sutherland-style clipping of a segment to a box around the image (with a margin for
/// line width); `None` when it misses. Keeps far-off endpoints from costing millions of steps.
fn clip(a: (f32, f32), b: (f32, f32), w: f32, h: f32) -> Option<((f32, f32), (f32, f32))> {
    if ![a.0, a.1, b.0, b.1].iter().all(|v| v.is_finite()) {
        return None;
    }
    let (xmin, ymin, xmax, ymax) = (-4.0, -4.0, w + 4.0, h + 4.0);
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    for (p, q) in [
        (-dx, a.0 - xmin),
        (dx, xmax - a.0),
        (-dy, a.1 - ymin),
        (dy, ymax - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then_some((
        (a.0 + dx * t0, a.1 + dy * t0),
        (a.0 + dx * t1, a.1 + dy * t1),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_land_where_asked_and_clip() {
        let mut c = Canvas::new(32, 16);
        c.disc(8.0, 8.0, 3.0, [255, 0, 0, 255]);
        assert_eq!(c.get(8, 8), [255, 0, 0, 255]);
        assert_eq!(c.get(20, 8)[3], 0);
        c.line((-1e9, 2.0), (1e9, 2.0), 1.0, [0, 255, 0, 255]);
        assert_eq!(c.get(31, 2), [0, 255, 0, 255]);
        c.line((f32::NAN, 0.0), (3.0, 3.0), 1.0, [0, 0, 255, 255]);
        let w = c.text(0, 8, "A", 1, [255, 255, 255, 255]);
        assert_eq!(w, 8);
        assert!((0..8).any(|x| (8..16).any(|y| c.get(x, y) == [255, 255, 255, 255])));
        // Half-transparent over opaque keeps it opaque and mixes the colour.
        c.blend(20, 10, [0, 0, 0, 255]);
        c.blend(20, 10, [255, 255, 255, 128]);
        let p = c.get(20, 10);
        assert_eq!(p[3], 255);
        assert!((120..=135).contains(&p[0]), "{p:?}");
        c.rect(-5, -5, 1000, 1000, [1, 2, 3, 4]);
    }
}
