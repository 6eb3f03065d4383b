//! Orbit camera in grid units: yaw/pitch/distance around a target point, +Y up,
//! right-handed, projecting to wgpu clip space (depth 0..1).

use glam::camera::rh::{proj::directx, view};
use glam::{Mat4, Vec3};

/// Radians of orbit per pixel of pointer drag.
const ORBIT_RADIANS_PER_PIXEL: f32 = 0.008;
const MAX_PITCH: f32 = 1.55;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrbitCamera {
    pub target: Vec3,
    /// Rotation about +Y; 0 looks from +Z towards -Z.
    pub yaw: f32,
    /// Elevation above the target's horizontal plane.
    pub pitch: f32,
    pub distance: f32,
    /// Vertical field of view in radians.
    pub fov_y: f32,
    /// Radius of the scene around `target` when framed; bounds zoom and the depth range.
    pub scene_radius: f32,
}

impl OrbitCamera {
    /// The default view of a scene whose voxels lie in the grid-unit box `min..max`:
    /// a three-quarter view from the front, slightly above, the whole box in view.
    pub fn framing(min: Vec3, max: Vec3) -> Self {
        let target = (min + max) * 0.5;
        let radius = ((max - min).length() * 0.5).max(1.0);
        let fov_y = 45f32.to_radians();
        Self {
            target,
            yaw: 35f32.to_radians(),
            pitch: 20f32.to_radians(),
            // The bounding sphere touches the frustum at 1/sin(fov/2); 5% margin.
            distance: radius / (fov_y * 0.5).sin() * 1.05,
            fov_y,
            scene_radius: radius,
        }
    }

    /// Moves along the view direction until the box `min..max` just fits a
    /// view of `aspect` (width / height), with a 5% margin: boxes of scans are
    /// rarely full, so this frames them much tighter than their bounding sphere.
    pub fn fit_box(&mut self, min: Vec3, max: Vec3, aspect: f32) {
        let tan_v = (self.fov_y * 0.5).tan();
        let tan_h = tan_v * aspect.max(1e-3);
        let forward = self.forward();
        let right = forward.cross(Vec3::Y).normalize_or(Vec3::X);
        let up = right.cross(forward);
        let needed = (0..8)
            .map(|i| {
                let corner = Vec3::select(glam::BVec3::new(i & 1 != 0, i & 2 != 0, i & 4 != 0), max, min);
                let o = corner - self.target;
                // Distance at which this corner sits on the edge of the view.
                -o.dot(forward) + (o.dot(right).abs() / tan_h).max(o.dot(up).abs() / tan_v)
            })
            .fold(0f32, f32::max);
        self.distance = (needed * 1.05).max(self.scene_radius * 0.05);
    }

    pub fn forward(&self) -> Vec3 {
        -self.offset_direction()
    }

    fn offset_direction(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        Vec3::new(cp * sy, sp, cp * cy)
    }

    pub fn eye(&self) -> Vec3 {
        self.target + self.offset_direction() * self.distance
    }

    pub fn view(&self) -> Mat4 {
        view::look_at_mat4(self.eye(), self.target, Vec3::Y)
    }

    /// Near and far planes hugging the scene sphere, so depth precision follows the zoom.
    pub fn depth_range(&self) -> (f32, f32) {
        let r = self.scene_radius * 1.5;
        let near = (self.distance - r).max(self.distance * 0.01).max(1e-3);
        let far = (self.distance + r).max(near * 2.0);
        (near, far)
    }

    pub fn projection(&self, aspect: f32) -> Mat4 {
        let (near, far) = self.depth_range();
        directx::perspective(self.fov_y, aspect.max(1e-3), near, far)
    }

    /// Grid units → wgpu clip space (depth 0..1).
    pub fn view_proj(&self, aspect: f32) -> Mat4 {
        self.projection(aspect) * self.view()
    }

    /// Pixels per grid unit at distance 1 for a viewport `height_px` tall.
    pub fn focal_pixels(&self, height_px: f32) -> f32 {
        height_px / (2.0 * (self.fov_y * 0.5).tan())
    }

    /// Drag by (dx, dy) pixels: right turns the scene right, down tilts it towards the viewer.
    pub fn orbit(&mut self, dx: f32, dy: f32) {
        self.yaw -= dx * ORBIT_RADIANS_PER_PIXEL;
        self.pitch = (self.pitch + dy * ORBIT_RADIANS_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
    }

    /// Multiplies the distance by `factor` (< 1 moves closer), within sane bounds.
    pub fn zoom(&mut self, factor: f32) {
        if !factor.is_finite() || factor <= 0.0 {
            return;
        }
        let min = self.scene_radius * 0.01;
        let max = self.scene_radius * 20.0;
        self.distance = (self.distance * factor).clamp(min, max);
    }

    /// Double-click: the orbit turns about `point` from where the eye is now;
    /// the eye stays (up to the pitch limit) and looks at the point.
    pub fn recentre(&mut self, point: Vec3) {
        let offset = self.eye() - point;
        let distance = offset.length();
        if !distance.is_finite() || distance < 1e-4 {
            return;
        }
        let d = offset / distance;
        self.yaw = d.x.atan2(d.z);
        self.pitch = d.y.clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH);
        self.target = point;
        self.distance = distance.max(self.scene_radius * 0.01);
    }

    /// Moves the target so the scene follows a drag of (dx, dy) pixels.
    pub fn pan(&mut self, dx: f32, dy: f32, viewport_height: f32) {
        let units_per_pixel = self.distance / self.focal_pixels(viewport_height.max(1.0));
        let forward = self.forward();
        let right = forward.cross(Vec3::Y).normalize_or(Vec3::X);
        let up = right.cross(forward);
        self.target += (-right * dx + up * dy) * units_per_pixel;
    }
}

impl OrbitCamera {
    /// Fly mode: moves eye and target together by `forward`, `right` and
    /// `up` grid units along the view axes (WASD, Q/E).
    pub fn fly(&mut self, forward: f32, right: f32, up: f32) {
        let f = self.forward();
        let r = f.cross(Vec3::Y).normalize_or(Vec3::X);
        self.target += f * forward + r * right + Vec3::Y * up;
    }

    /// Fly speed: a scene crossed in about ten seconds, in grid units per second.
    pub fn fly_speed(&self) -> f32 {
        self.scene_radius * 0.2
    }

    /// Mouse look: turns the view about the eye (the eye stays put) by a drag of (dx, dy) pixels.
    pub fn look(&mut self, dx: f32, dy: f32) {
        let eye = self.eye();
        self.yaw -= dx * ORBIT_RADIANS_PER_PIXEL * 0.5;
        self.pitch = (self.pitch - dy * ORBIT_RADIANS_PER_PIXEL * 0.5).clamp(-MAX_PITCH, MAX_PITCH);
        self.target = eye + self.forward() * self.distance;
    }

    /// The view as URL text: target x, y, z, yaw, pitch, distance.
    pub fn to_url(&self) -> String {
        let t = self.target;
        format!("{:.3},{:.3},{:.3},{:.5},{:.5},{:.3}", t.x, t.y, t.z, self.yaw, self.pitch, self.distance)
    }

    /// Looks from `eye` at `target` (grid units, +Y up) with a vertical field
    /// of view of `fov_y_deg`: the orbit then turns about `target`. `false`,
    /// with the camera unchanged, where the two points coincide or anything is
    /// not finite or the angle is outside (0, 180).
    pub fn look_at(&mut self, eye: Vec3, target: Vec3, fov_y_deg: f32) -> bool {
        let offset = eye - target;
        let distance = offset.length();
        let valid = eye.is_finite()
            && target.is_finite()
            && distance.is_finite()
            && distance > 0.0
            && fov_y_deg > 0.0
            && fov_y_deg < 180.0;
        if !valid {
            return false;
        }
        let d = offset / distance;
        self.target = target;
        self.distance = distance;
        // Straight up or down has no yaw; the pitch clamp keeps the view's up defined.
        self.yaw = d.x.atan2(d.z);
        self.pitch = d.y.clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH);
        self.fov_y = fov_y_deg.to_radians();
        true
    }

    /// Applies `eye x,y,z,target x,y,z,fov_y_deg` given in a scene's source
    /// coordinates (a camera.json's eye, target and fov_y_deg, as the viewer's
    /// `?camera=` takes them) for the grid frame `origin`, `voxel_size`. The
    /// points are moved into grid units in f64 first, so georeferenced
    /// coordinates keep their precision. `false` (camera unchanged) unless
    /// there are exactly seven numbers that [`OrbitCamera::look_at`] accepts.
    pub fn apply_source_look_at(&mut self, text: &str, origin: [f64; 3], voxel_size: f64) -> bool {
        let Ok(v) = text.split(',').map(|x| x.trim().parse::<f64>()).collect::<Result<Vec<_>, _>>() else {
            return false;
        };
        let voxel_ok = voxel_size.is_finite() && voxel_size > 0.0;
        if v.len() != 7 || !voxel_ok {
            return false;
        }
        let to_grid = |p: &[f64]| {
            Vec3::new(
                ((p[0] - origin[0]) / voxel_size) as f32,
                ((p[1] - origin[1]) / voxel_size) as f32,
                ((p[2] - origin[2]) / voxel_size) as f32,
            )
        };
        self.look_at(to_grid(&v[0..3]), to_grid(&v[3..6]), v[6] as f32)
    }

    /// Applies a view from [`OrbitCamera::to_url`]; anything malformed leaves the camera as it is.
    pub fn apply_url(&mut self, text: &str) -> bool {
        let v: Vec<f32> = text.split(',').filter_map(|x| x.trim().parse().ok()).collect();
        if v.len() != 6 || v.iter().any(|x| !x.is_finite()) || v[5] <= 0.0 {
            return false;
        }
        self.target = Vec3::new(v[0], v[1], v[2]);
        self.yaw = v[3];
        self.pitch = v[4].clamp(-MAX_PITCH, MAX_PITCH);
        self.distance = v[5];
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec4;

    #[test]
    fn look_at_puts_the_eye_and_target_where_asked() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(100.0));
        let (eye, target) = (Vec3::new(10.0, 30.0, -40.0), Vec3::new(50.0, 20.0, 60.0));
        assert!(cam.look_at(eye, target, 60.0));
        assert!((cam.eye() - eye).length() < 1e-3, "{:?}", cam.eye());
        assert!((cam.target - target).length() < 1e-6);
        assert!((cam.forward() - (target - eye).normalize()).length() < 1e-5);
        assert!((cam.fov_y - 60f32.to_radians()).abs() < 1e-6);
        // The view matrix maps the target onto the view axis.
        let t = cam.view().transform_point3(target);
        assert!(t.x.abs() < 1e-3 && t.y.abs() < 1e-3 && t.z < 0.0, "{t:?}");
        // Controls: degenerate input is refused and leaves the camera as it was.
        let before = cam;
        assert!(!cam.look_at(eye, eye, 60.0));
        assert!(!cam.look_at(eye, Vec3::new(f32::NAN, 0.0, 0.0), 60.0));
        assert!(!cam.look_at(eye, target, 180.0));
        assert_eq!(cam, before);
    }

    #[test]
    fn a_source_look_at_lands_in_grid_units() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(256.0));
        // A georeferenced frame: origin 1e6 away, 0.5-unit voxels.
        let origin = [1.0e6, 2.0e6, -3.0e6];
        let text = "1000010,2000020,-2999990, 1000050,2000020,-2999990, 45";
        assert!(cam.apply_source_look_at(text, origin, 0.5));
        assert!((cam.eye() - Vec3::new(20.0, 40.0, 20.0)).length() < 1e-3, "{:?}", cam.eye());
        assert!((cam.target - Vec3::new(100.0, 40.0, 20.0)).length() < 1e-3);
        assert!((cam.fov_y - 45f32.to_radians()).abs() < 1e-6);
        // Controls: six numbers, a word among them, eight numbers, a zero voxel.
        let before = cam;
        assert!(!cam.apply_source_look_at("1,2,3,4,5,6", origin, 0.5));
        assert!(!cam.apply_source_look_at("1,2,x,4,5,6,45", origin, 0.5));
        assert!(!cam.apply_source_look_at("1,2,3,4,5,6,45,1", origin, 0.5));
        assert!(!cam.apply_source_look_at(text, origin, 0.0));
        assert_eq!(cam, before);
    }

    #[test]
    fn look_keeps_the_eye_and_fly_moves_along_the_view() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(100.0));
        let eye = cam.eye();
        cam.look(40.0, -25.0);
        assert!((cam.eye() - eye).length() < 1e-3, "look moved the eye");
        // Control: orbit by the same drag moves it.
        let mut orbited = cam;
        orbited.orbit(40.0, -25.0);
        assert!((orbited.eye() - cam.eye()).length() > 1.0);
        let before = cam.eye();
        cam.fly(10.0, 0.0, 0.0);
        let moved = cam.eye() - before;
        assert!((moved - cam.forward() * 10.0).length() < 1e-3, "fly forward moved by {moved}");
    }

    #[test]
    fn the_view_round_trips_through_the_url() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(100.0));
        cam.orbit(33.0, 12.0);
        cam.zoom(0.4);
        let mut other = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(100.0));
        assert!(other.apply_url(&cam.to_url()));
        assert!((other.eye() - cam.eye()).length() < 1e-2 && (other.target - cam.target).length() < 1e-2);
        let unchanged = other;
        for bad in ["", "1,2,3", "a,b,c,d,e,f", "1,2,3,4,5,-1", "1,2,3,4,5,NaN"] {
            assert!(!other.apply_url(bad), "{bad:?} accepted");
            assert_eq!(other, unchanged);
        }
    }

    fn project(m: Mat4, p: Vec3) -> Vec3 {
        let c = m * Vec4::new(p.x, p.y, p.z, 1.0);
        c.truncate() / c.w
    }

    #[test]
    fn framing_puts_the_box_inside_the_frustum() {
        let (min, max) = (Vec3::new(10.0, 0.0, 5.0), Vec3::new(500.0, 300.0, 400.0));
        let cam = OrbitCamera::framing(min, max);
        let vp = cam.view_proj(1.0);
        let centre = project(vp, cam.target);
        assert!(centre.x.abs() < 1e-4 && centre.y.abs() < 1e-4, "target at {centre}");
        for i in 0..8 {
            let corner = Vec3::new(
                if i & 1 == 0 { min.x } else { max.x },
                if i & 2 == 0 { min.y } else { max.y },
                if i & 4 == 0 { min.z } else { max.z },
            );
            let ndc = project(vp, corner);
            assert!(ndc.x.abs() <= 1.0 && ndc.y.abs() <= 1.0, "corner {corner} at {ndc}");
            assert!(ndc.z > 0.0 && ndc.z < 1.0, "corner {corner} depth {}", ndc.z);
        }
    }

    #[test]
    fn fit_box_is_tight_and_inside() {
        let (min, max) = (Vec3::new(0.0, 0.0, 0.0), Vec3::new(200.0, 120.0, 400.0));
        for aspect in [0.5, 1.0, 1.6] {
            let mut cam = OrbitCamera::framing(min, max);
            cam.fit_box(min, max, aspect);
            let vp = cam.view_proj(aspect);
            let mut widest: f32 = 0.0;
            for i in 0..8 {
                let corner = Vec3::select(glam::BVec3::new(i & 1 != 0, i & 2 != 0, i & 4 != 0), max, min);
                let ndc = project(vp, corner);
                assert!(ndc.x.abs() <= 1.0 && ndc.y.abs() <= 1.0, "aspect {aspect}: corner at {ndc}");
                assert!(ndc.z > 0.0 && ndc.z < 1.0, "aspect {aspect}: corner depth {}", ndc.z);
                widest = widest.max(ndc.x.abs()).max(ndc.y.abs());
            }
            assert!(widest > 0.9, "aspect {aspect}: the box only reaches {widest} of the view");
        }
    }

    #[test]
    fn depth_is_zero_to_one_and_y_is_up() {
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(100.0));
        let vp = cam.view_proj(1.5);
        let (near, far) = cam.depth_range();
        let f = cam.forward();
        let at_near = project(vp, cam.eye() + f * near);
        let at_far = project(vp, cam.eye() + f * far);
        assert!(at_near.z.abs() < 1e-4, "near maps to {}", at_near.z);
        assert!((at_far.z - 1.0).abs() < 1e-4, "far maps to {}", at_far.z);
        let above = project(vp, cam.target + Vec3::Y * 10.0);
        assert!(above.y > 0.0, "a point above the target must be above the centre");
    }

    #[test]
    fn orbit_keeps_distance_and_clamps_pitch() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(64.0));
        let d = cam.eye().distance(cam.target);
        cam.orbit(120.0, 10_000.0);
        assert!((cam.eye().distance(cam.target) - d).abs() < 1e-3);
        assert!(cam.pitch <= MAX_PITCH);
        // Near the pole the view matrix must still be finite.
        assert!(cam.view_proj(1.0).is_finite());
    }

    #[test]
    fn zoom_is_bounded_and_ignores_garbage() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(64.0));
        let d = cam.distance;
        cam.zoom(f32::NAN);
        cam.zoom(-2.0);
        assert_eq!(cam.distance, d);
        for _ in 0..100 {
            cam.zoom(0.5);
        }
        assert!(cam.distance >= cam.scene_radius * 0.01 - 1e-6);
        assert!(cam.view_proj(1.0).is_finite());
    }

    #[test]
    fn pan_moves_the_target_with_the_pointer() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(64.0));
        let before = cam.target;
        let vp = cam.view_proj(1.0);
        cam.pan(50.0, 0.0, 500.0);
        // Dragging right moves the scene right, i.e. the old target now projects right of centre.
        let new_vp = cam.view_proj(1.0);
        let old_target_now = project(new_vp, before);
        assert!(old_target_now.x > 0.0, "old target at {old_target_now}");
        // 50 px of a 500 px viewport is 0.2 NDC units at the target's depth.
        assert!((old_target_now.x - 0.2).abs() < 1e-3, "moved to {}", old_target_now.x);
        assert!(project(vp, before).x.abs() < 1e-4);
    }

    #[test]
    fn recentre_keeps_the_eye_and_puts_the_point_at_the_centre() {
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(64.0));
        let eye = cam.eye();
        let point = Vec3::new(10.0, 50.0, 20.0);
        assert!(project(cam.view_proj(1.0), point).truncate().length() > 0.05, "the point starts off-centre");
        cam.recentre(point);
        assert!((cam.eye() - eye).length() < 1e-3 * eye.length(), "the eye moved: {} vs {eye}", cam.eye());
        assert_eq!(cam.target, point);
        assert!(project(cam.view_proj(1.0), point).truncate().length() < 1e-4);
        // Orbiting now turns about the point: its distance from the eye stays.
        cam.orbit(40.0, 10.0);
        assert!(((cam.eye() - point).length() - (eye - point).length()).abs() < 1e-3);
        // Control: the eye itself is no centre; nothing changes.
        let before = cam;
        cam.recentre(cam.eye());
        assert_eq!(cam, before);
    }
}
