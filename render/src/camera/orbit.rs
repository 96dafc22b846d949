//! A turntable's orbit: one distance for every view, so the cloud neither zooms in and out nor
//! leaves the frame as it turns, and in each view the camera panned so the cloud sits in the
//! middle of the image, as a still's automatic view centres it.
//!
//! Looking at one point on the vertical axis from every side cannot centre a cloud: its
//! projection's middle moves with the azimuth (perspective draws the near end larger, a long
//! subject seen end-on reaches lower than seen side-on), so the orbit would have to stand back
//! far enough for the emptier side of every view. The automatic orbit instead keeps the camera
//! a fixed distance in front of the box's centre along each view direction and shifts it across
//! the view, which centres every frame and lets the widest view come as close as a still's.

use glam::DVec3;

use super::{view_direction, BoxView, Projection, FRAMING_MARGIN};
use crate::cloud::WorldBounds;

/// Room the automatic orbit leaves around the cloud's outline: 8% of the image's half-side
/// rather than a still's 5%, because a frame between the views the orbit is fitted to sees
/// the cloud a little wider, and points are drawn as squares of up to eight pixels around
/// their projections, which at small sizes is more than 5% of the image.
const ORBIT_MARGIN: f64 = 1.08;

/// Where a turntable's camera circles the vertical axis through `center`, and how it aims.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    /// The point the orbit turns around; the box's centre for the automatic orbit.
    pub center: DVec3,
    /// The camera's distance from `center` along its viewing direction.
    pub distance: f64,
    /// Whether each view is panned to centre the cloud (the automatic orbit) or looks at
    /// `center` (a centre given by hand, or an orthographic lens, whose scale the distance
    /// does not change).
    pub centred: bool,
}

impl Orbit {
    /// The camera's position and target at `azimuth_deg` (counter-clockwise from +X) and
    /// `elevation_deg` (above the horizon) on this orbit around `outline` (points of a cloud
    /// in `bounds`, world coordinates).
    pub fn view(
        &self,
        bounds: &WorldBounds,
        outline: &[DVec3],
        azimuth_deg: f64,
        elevation_deg: f64,
    ) -> (DVec3, DVec3) {
        let direction = view_direction(azimuth_deg, elevation_deg);
        let target = if self.centred {
            let view = BoxView::new(bounds, outline, azimuth_deg, elevation_deg);
            let (sideways, upwards) = view.centring(-self.distance);
            self.center + view.right * sideways + view.up * upwards
        } else {
            self.center
        };
        (target + direction * self.distance, target)
    }
}

/// The orbit that sees all of `outline` (points of a cloud in `bounds`, world coordinates: its
/// box's corners, or its outermost points) from each of `azimuths` (degrees counter-clockwise
/// from +X) at `elevation_deg`, as close as the widest of those views lets every point stay in
/// the image. Around a given `center` the camera looks at it, with a still's 5% margin, as it
/// always has; otherwise the orbit is centred on the box ([`Orbit::view`] pans each view) and
/// keeps [`ORBIT_MARGIN`].
pub fn fitted_orbit(
    bounds: &WorldBounds,
    outline: &[DVec3],
    center: Option<DVec3>,
    aspect: f64,
    azimuths: &[f64],
    elevation_deg: f64,
    projection: Projection,
) -> Orbit {
    let radius = bounds.radius().max(1e-3);
    let Projection::Perspective { fov_y_deg } = projection else {
        // An orthographic image's scale does not depend on the distance: only the clip planes
        // need the camera outside the box.
        return Orbit {
            center: center.unwrap_or(bounds.center()),
            distance: radius * 2.0,
            centred: false,
        };
    };
    let tan = (fov_y_deg.to_radians() * 0.5).tan();
    let views: Vec<BoxView> = azimuths
        .iter()
        .map(|&azimuth| BoxView::new(bounds, outline, azimuth, elevation_deg))
        .collect();
    let Some(center) = center else {
        let tan_y = tan / ORBIT_MARGIN;
        let distance = views
            .iter()
            .map(|view| -view.fitted_depth(tan_y * aspect, tan_y))
            .fold(radius * 0.01, f64::max);
        return Orbit {
            center: bounds.center(),
            distance,
            centred: true,
        };
    };
    let tan_y = tan / FRAMING_MARGIN;
    let tan_x = tan_y * aspect;
    let offset = bounds.center() - center;
    // Each point's lateral offsets from the given centre within the field of view at its
    // depth, c·forward plus the distance.
    let distance = views
        .iter()
        .flat_map(|view| {
            view.corners.iter().map(move |&c| {
                let c = c + offset;
                let fit = (c.dot(view.up).abs() / tan_y).max(c.dot(view.right).abs() / tan_x);
                fit - c.dot(view.forward)
            })
        })
        .fold(radius * 0.01, f64::max);
    Orbit {
        center,
        distance,
        centred: false,
    }
}
