//! Shape primitives the anatomy is drawn with: approximate signed distances (mm, negative
//! inside) of ovals, ellipsoids and tapered capsules, the soft partial-volume occupancy of a
//! signed distance, the layer blending rule ([`Mix`]), and smooth z-profiles ([`Profile`]).
//!
//! Signed distances here are first-order: exact in sign, close to true millimetres near the
//! surface (where occupancy ramps and thin shells are evaluated), rougher far from it.

use super::Tissue;
use glam::Vec3;

/// A point or direction in patient mm, as the anatomy's tables write it; arithmetic goes
/// through glam's `Vec3`.
pub(crate) type V3 = [f32; 3];

/// Fraction of a voxel inside a surface at signed distance `sd_mm` from the voxel centre:
/// a linear ramp one `edge_mm` wide, centred on the surface (partial volume).
pub(crate) fn occupancy(sd_mm: f32, edge_mm: f32) -> f32 {
    (0.5 - sd_mm / edge_mm).clamp(0.0, 1.0)
}

/// Signed distance to a 2-D oval with half-axes `a` (x) and `b` (y), `squareness` in [0, 1]
/// blending an ellipse (0) into a rounded square (1, the 4-norm): the body wall and the
/// thoracic cavity are boxier than ellipses.
pub(crate) fn oval_sd(dx: f32, dy: f32, a: f32, b: f32, squareness: f32) -> f32 {
    let (u, v) = (dx / a, dy / b);
    let r2 = (u * u + v * v).sqrt();
    if r2 < 1e-6 {
        return -a.min(b);
    }
    let (u2, v2) = (u * u, v * v);
    let r4 = (u2 * u2 + v2 * v2).sqrt().sqrt();
    let r = (1.0 - squareness) * r2 + squareness * r4;
    let r4_3 = r4 * r4 * r4;
    // Gradient of r with respect to (dx, dy): dividing by its length turns the level-set
    // value into millimetres near the surface.
    let gx = (1.0 - squareness) * u / (a * r2) + squareness * u * u2 / (a * r4_3);
    let gy = (1.0 - squareness) * v / (b * r2) + squareness * v * v2 / (b * r4_3);
    (r - 1.0) / (gx * gx + gy * gy).sqrt().max(1e-6)
}

/// Signed distance to an axis-aligned ellipsoid with half-axes `semi` around the origin.
pub(crate) fn ellipsoid_sd(d: V3, semi: V3) -> f32 {
    let (d, semi) = (Vec3::from(d), Vec3::from(semi));
    let q = d / semi;
    let r = q.length();
    if r < 1e-6 {
        return -semi.min_element();
    }
    let g = q / (semi * r);
    (r - 1.0) / g.length().max(1e-6)
}

/// Signed distance to a capsule from `a` (radius `ra`) to `b` (radius `rb`), radius linear
/// along the axis: one segment of a tapering tube.
pub(crate) fn capsule_sd(p: V3, a: V3, b: V3, ra: f32, rb: f32) -> f32 {
    let (p, a, b) = (Vec3::from(p), Vec3::from(a), Vec3::from(b));
    let ab = b - a;
    let len2 = ab.dot(ab);
    let t = if len2 > 0.0 { ((p - a).dot(ab) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (p - (a + ab * t)).length() - (ra + t * (rb - ra))
}

/// Signed distance to the slab `lo ≤ x ≤ hi`.
pub(crate) fn interval_sd(x: f32, lo: f32, hi: f32) -> f32 {
    (lo - x).max(x - hi)
}

/// A quantity that varies smoothly with height: keyframes `(z_mm, value)`, ascending in z,
/// joined by smoothsteps and held constant beyond the ends.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Profile(pub &'static [(f32, f32)]);

impl Profile {
    pub(crate) fn at(&self, z: f32) -> f32 {
        let keys = self.0;
        let first = keys[0];
        if z <= first.0 {
            return first.1;
        }
        for pair in keys.windows(2) {
            let ((z0, v0), (z1, v1)) = (pair[0], pair[1]);
            if z <= z1 {
                let t = (z - z0) / (z1 - z0);
                return v0 + (v1 - v0) * t * t * (3.0 - 2.0 * t);
            }
        }
        keys[keys.len() - 1].1
    }
}

/// What one layer contributes to a voxel: the fraction it covers, the HU of what covers it,
/// and its tissue (for labels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Sample {
    pub occupancy: f32,
    pub hu: f32,
    pub tissue: Tissue,
}

/// Paints parts over one another: each part replaces the fraction `occupancy` of what is
/// below it (`hu ← (1 − o)·hu + o·part_hu`). Accumulated as `hu = keep·below + add`, so a
/// composite of parts is itself one [`Sample`] that blends the same way.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Mix {
    keep: f32,
    add: f32,
    tissue: Option<(Tissue, f32)>,
}

impl Mix {
    pub(crate) fn new() -> Mix {
        Mix { keep: 1.0, add: 0.0, tissue: None }
    }

    /// Paint a part covering `occupancy` of the voxel with `hu`.
    pub(crate) fn paint(&mut self, occupancy: f32, hu: f32, tissue: Tissue) {
        if occupancy <= 0.0 {
            return;
        }
        self.add = self.add * (1.0 - occupancy) + occupancy * hu;
        self.keep *= 1.0 - occupancy;
        // The label is the last part covering at least half the voxel; failing that, the
        // part covering most of it.
        let replace = match self.tissue {
            None => true,
            Some((_, o)) => occupancy >= 0.5 || occupancy >= o,
        };
        if replace {
            self.tissue = Some((tissue, occupancy));
        }
    }

    pub(crate) fn paint_sample(&mut self, sample: Option<Sample>) {
        if let Some(s) = sample {
            self.paint(s.occupancy, s.hu, s.tissue);
        }
    }

    /// The composite as one sample; `None` if nothing was painted.
    pub(crate) fn sample(&self) -> Option<Sample> {
        let occupancy = 1.0 - self.keep;
        let (tissue, _) = self.tissue?;
        (occupancy > 0.0).then(|| Sample { occupancy, hu: self.add / occupancy, tissue })
    }

    pub(crate) fn tissue(&self) -> Option<Tissue> {
        self.tissue.map(|(t, _)| t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oval_distance_is_millimetres_near_the_surface() {
        for squareness in [0.0, 0.5, 1.0] {
            // On the axes the surface is at x = a.
            let d = oval_sd(102.0, 0.0, 100.0, 60.0, squareness);
            assert!((d - 2.0).abs() < 0.05, "{squareness}: {d}");
            let d = oval_sd(0.0, -57.0, 100.0, 60.0, squareness);
            assert!((d + 3.0).abs() < 0.1, "{squareness}: {d}");
        }
    }

    #[test]
    fn mix_of_parts_blends_like_painting_them_in_turn() {
        let below = -1000.0;
        let mut painted = below;
        let mut mix = Mix::new();
        for (o, hu) in [(0.3, 40.0), (0.8, -100.0), (0.5, 700.0)] {
            painted = (1.0 - o) * painted + o * hu;
            mix.paint(o, hu, Tissue::Muscle);
        }
        let s = mix.sample().unwrap();
        let composite = (1.0 - s.occupancy) * below + s.occupancy * s.hu;
        assert!((composite - painted).abs() < 1e-3, "{composite} vs {painted}");
    }

    #[test]
    fn profile_interpolates_between_keys() {
        let p = Profile(&[(0.0, 10.0), (10.0, 20.0)]);
        assert_eq!(p.at(-5.0), 10.0);
        assert_eq!(p.at(5.0), 15.0);
        assert_eq!(p.at(50.0), 20.0);
    }
}
