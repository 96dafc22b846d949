//! The exposure after Eye-Dome Lighting, measured or held: a held gain is applied exactly as a
//! measured one, on the GPU and in the CPU reference, and a gain outside its range is refused.

use super::*;
use crate::ingest::load_point_cloud;
use crate::raster::exposure::{luma_bin, MAX_GAIN};
use crate::testing::{compare_images_within, gpu, shared_data};

/// An EDL frame of the Autzen scan from the automatic camera turned by `degrees`.
fn autzen_settings(cloud: &PointCloud, degrees: f64) -> FrameSettings {
    let (w, h) = (320, 180);
    FrameSettings {
        point_size: 2,
        shading: Shading::EDL,
        ..FrameSettings::new(
            w,
            h,
            Camera::auto(&cloud.bounds, w as f64 / h as f64).orbit(degrees),
        )
    }
}

fn held(settings: &FrameSettings, gain: f32) -> FrameSettings {
    FrameSettings {
        exposure: Exposure::Held(gain),
        ..*settings
    }
}

#[test]
fn a_held_gain_exposes_the_frame_as_the_measured_one_and_as_the_reference() {
    let Some(path) = shared_data("autzen_trim.laz") else {
        return;
    };
    let cloud = load_point_cloud(&path).expect("the scan");
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let settings = autzen_settings(&cloud, 0.0);
    let measured = renderer.render(&resident, &settings).expect("measured");
    let gain = measured.gain.expect("an EDL frame reports its gain");
    // The scan's slopes and trees darken under EDL: the exposure brightens it back.
    assert!(gain > 1.05, "gain {gain}");

    let again = renderer
        .render(&resident, &held(&settings, gain))
        .expect("held");
    assert_eq!(again.gain, Some(gain));
    assert!(
        again.image == measured.image,
        "the held gain exposes the frame differently from the measured one"
    );

    // Another frame's gain is applied as given, not measured anew.
    let brighter = (gain * 1.25).min(MAX_GAIN);
    let lifted = renderer
        .render(&resident, &held(&settings, brighter))
        .expect("held brighter");
    assert_eq!(lifted.gain, Some(brighter));
    let luma = |image: &image::RgbaImage| {
        image
            .pixels()
            .map(|p| luma_bin(p[0], p[1], p[2]) as u64)
            .sum::<u64>()
    };
    assert!(luma(&lifted.image) > luma(&measured.image));

    for (name, gain) in [("measured", gain), ("brighter", brighter)] {
        let settings = held(&settings, gain);
        let frame = renderer.render(&resident, &settings).expect("render");
        let expected = reference::render(&cloud, &settings);
        assert_eq!(expected.gain, Some(gain));
        let name = format!("held-{name}-gain");
        let diff = compare_images_within(&name, &frame.image, &expected.image, 2);
        assert!(diff.equal_fraction() >= 0.995, "{name}: {diff:?}");
    }
    let reference_measured = reference::render(&cloud, &settings);
    let reference_gain = reference_measured.gain.expect("the reference's gain");
    assert!(
        (reference_gain - gain).abs() < 0.02,
        "the reference measures {reference_gain}, the GPU {gain}"
    );

    let unshaded = FrameSettings {
        shading: Shading::None,
        ..settings
    };
    let plain = renderer.render(&resident, &unshaded).expect("unshaded");
    assert_eq!(plain.gain, None, "only EDL frames are exposed");
}

#[test]
fn a_held_gain_outside_its_range_is_refused_with_its_reason() {
    let cloud = pixel_centre_scene(&perspective_settings(32, 24), 1, 3);
    let (mut renderer, resident) = uploaded(&cloud);
    let settings = FrameSettings {
        shading: Shading::EDL,
        ..perspective_settings(32, 24)
    };
    for gain in [f32::NAN, 0.0, 0.5, -1.0, MAX_GAIN + 0.01, f32::INFINITY] {
        let error = renderer
            .render(&resident, &held(&settings, gain))
            .expect_err("an invalid gain");
        assert!(
            matches!(error, RenderError::ExposureGain(g) if g.to_bits() == gain.to_bits()),
            "{gain}: {error:?}"
        );
        let message = error.to_string();
        assert!(
            message.contains("held exposure gain") && message.contains("from 1 to 4"),
            "{message}"
        );
    }
    for gain in [1.0, MAX_GAIN] {
        let frame = renderer
            .render(&resident, &held(&settings, gain))
            .expect("a gain at its bounds");
        assert_eq!(frame.gain, Some(gain));
    }
}
