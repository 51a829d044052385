//! Axis-aligned boxes around the scene, and where rays enter and leave them.

use glam::Vec3;

use crate::scene::Ray;

/// An axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn new(min: Vec3, max: Vec3) -> Self {
        Self { min, max }
    }

    /// A cube centred at `centre` with half side `half`.
    pub fn cube(centre: Vec3, half: f32) -> Self {
        Self::new(centre - Vec3::splat(half), centre + Vec3::splat(half))
    }

    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }

    pub fn centre(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    pub fn contains(&self, point: Vec3) -> bool {
        point.cmpge(self.min).all() && point.cmple(self.max).all()
    }

    /// The parameter interval `[t_enter, t_exit]` (with `t_enter ≥ t_min`)
    /// where `origin + t · direction` is inside the box, or `None` when the
    /// ray misses it. Direction components may be zero: such a ray is inside
    /// the slab for every `t` when its origin is, and never otherwise.
    pub fn intersect(&self, origin: Vec3, direction: Vec3, t_min: f32) -> Option<(f32, f32)> {
        let mut t_enter = t_min;
        let mut t_exit = f32::INFINITY;
        for axis in 0..3 {
            let (o, d) = (origin[axis], direction[axis]);
            let (lo, hi) = (self.min[axis], self.max[axis]);
            if d == 0.0 {
                if o < lo || o > hi {
                    return None;
                }
                continue;
            }
            let inverse = 1.0 / d;
            let (mut t0, mut t1) = ((lo - o) * inverse, (hi - o) * inverse);
            if t0 > t1 {
                std::mem::swap(&mut t0, &mut t1);
            }
            t_enter = t_enter.max(t0);
            t_exit = t_exit.min(t1);
        }
        (t_enter <= t_exit).then_some((t_enter, t_exit))
    }

    /// [`Self::intersect`] for a [`Ray`] along its unit direction.
    pub fn intersect_ray(&self, ray: &Ray, t_min: f32) -> Option<(f32, f32)> {
        self.intersect(ray.origin, ray.direction, t_min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ray_through_centre_enters_and_leaves_at_faces() {
        let b = Aabb::cube(Vec3::ZERO, 1.0);
        let (t0, t1) = b
            .intersect(Vec3::new(0.0, 0.0, 5.0), -Vec3::Z, 0.0)
            .unwrap();
        assert!((t0 - 4.0).abs() < 1e-6 && (t1 - 6.0).abs() < 1e-6);
    }

    #[test]
    fn ray_missing_box_is_none() {
        let b = Aabb::cube(Vec3::ZERO, 1.0);
        assert!(
            b.intersect(Vec3::new(3.0, 0.0, 5.0), -Vec3::Z, 0.0)
                .is_none()
        );
        // Pointing away.
        assert!(
            b.intersect(Vec3::new(0.0, 0.0, 5.0), Vec3::Z, 0.0)
                .is_none()
        );
    }

    #[test]
    fn ray_starting_inside_enters_at_t_min() {
        let b = Aabb::cube(Vec3::ZERO, 1.0);
        let (t0, t1) = b.intersect(Vec3::ZERO, Vec3::X, 0.0).unwrap();
        assert_eq!(t0, 0.0);
        assert!((t1 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn axis_parallel_ray_on_a_face_plane() {
        let b = Aabb::cube(Vec3::ZERO, 1.0);
        // Runs along the face x = 1: inside (boxes are closed).
        let hit = b
            .intersect(Vec3::new(1.0, 0.0, 5.0), -Vec3::Z, 0.0)
            .unwrap();
        assert!(hit.0.is_finite() && hit.1.is_finite());
        // Just outside that face: a miss, and no NaN anywhere.
        assert!(
            b.intersect(Vec3::new(1.0001, 0.0, 5.0), -Vec3::Z, 0.0)
                .is_none()
        );
    }
}
