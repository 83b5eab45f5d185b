//! The rig in 3D for the viewer (`rig3d/...`, mm): each coil as its winding's cylinder (outer
//! radius, length along its axis) coloured by the current control commands (red positive, blue
//! negative, grey idle; full colour at the coil's limit), the canal's outline on the workspace
//! plane, the capsule, and the field and force control asks for at it. Control draws it because
//! it holds both the rig file and the commands; coils without a winding in the rig file (field
//! maps only) are drawn at a nominal size.

use fieldmaps::rigfile::Rig;
use millinav_kit::rerun;
use nalgebra::{UnitQuaternion, Vector3};
use shm_schemas::{CoilCommand, Pose};

/// Coil size drawn when the rig file gives no winding, mm (radius, length).
const NOMINAL_COIL_MM: (f32, f32) = (25.0, 40.0);

/// Arrow length of the field and force directions, mm.
const ARROW_MM: f32 = 12.0;

fn mm(v: &Vector3<f64>) -> [f32; 3] {
    [(v.x * 1e3) as f32, (v.y * 1e3) as f32, (v.z * 1e3) as f32]
}

/// Logs what does not change: the canal's outline at z = 0.
pub fn log_static(rec: &rerun::RecordingStream, rig: &Rig) {
    let outline: Vec<[f32; 3]> = rig
        .phantom
        .mask
        .outline_m(3)
        .iter()
        .map(|p| [(p.x * 1e3) as f32, (p.y * 1e3) as f32, 0.0])
        .collect();
    let _ = rec.log_static(
        "rig3d/canal",
        &rerun::Points3D::new(outline)
            .with_radii([0.2])
            .with_colors([rerun::Color::from_rgb(120, 110, 100)]),
    );
}

/// Red for positive, blue for negative current, grey at zero; saturated at `limit_a`.
fn current_colour(current_a: f64, limit_a: f64) -> rerun::Color {
    let k = (current_a.abs() / limit_a.max(1e-9)).min(1.0);
    let grey = 170.0;
    let mix = |full: f64| (grey + (full - grey) * k).round() as u8;
    if current_a >= 0.0 {
        rerun::Color::from_rgb(mix(220.0), mix(40.0), mix(40.0))
    } else {
        rerun::Color::from_rgb(mix(40.0), mix(70.0), mix(220.0))
    }
}

/// Logs the coils coloured by `command`'s currents (rig coil `ids[k]` carries entry k), the
/// capsule at `pose` and the commanded field and force directions there.
pub fn log_state(
    rec: &rerun::RecordingStream,
    rig: &Rig,
    ids: &[usize],
    command: &CoilCommand,
    pose: &Pose,
    robot_length_m: f64,
    robot_radius_m: f64,
) {
    let currents = command.currents().unwrap_or_default();
    let mut current_of = vec![0.0; rig.coils.len()];
    for (&id, &c) in ids.iter().zip(currents) {
        if let Some(slot) = current_of.get_mut(id) {
            *slot = c;
        }
    }
    let z = Vector3::z();
    let (mut centers, mut lengths, mut radii, mut rotations, mut colours, mut labels) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for (coil, &current) in rig.coils.iter().zip(&current_of) {
        let (radius, length) = coil.winding.map_or(NOMINAL_COIL_MM, |w| {
            ((w.outer_radius_m * 1e3) as f32, (w.length_m * 1e3) as f32)
        });
        let q = UnitQuaternion::rotation_between(&z, &coil.axis).unwrap_or_else(|| {
            // Antiparallel to z: half a turn about x.
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
        });
        let q = q.quaternion();
        centers.push(mm(&coil.center_m));
        lengths.push(length);
        radii.push(radius);
        rotations.push(rerun::Quaternion::from_xyzw([
            q.i as f32, q.j as f32, q.k as f32, q.w as f32,
        ]));
        colours.push(current_colour(current, coil.max_current_a));
        labels.push(format!("{} {current:+.1} A", coil.name));
    }
    let _ = rec.log(
        "rig3d/coils",
        &rerun::Cylinders3D::from_lengths_and_radii(lengths, radii)
            .with_centers(centers)
            .with_quaternions(rotations)
            .with_colors(colours)
            .with_labels(labels),
    );
    if !pose.is_usable() {
        return;
    }
    let (x, y, h) = (pose.position_m[0], pose.position_m[1], pose.heading_rad);
    let half = robot_length_m / 2.0 - robot_radius_m;
    let at = |s: f64| {
        [
            ((x + s * h.cos()) * 1e3) as f32,
            ((y + s * h.sin()) * 1e3) as f32,
            (robot_radius_m * 1e3) as f32,
        ]
    };
    let _ = rec.log(
        "rig3d/robot",
        &rerun::Capsules3D::from_endpoints_and_radii(
            [at(-half)],
            [at(half)],
            [(robot_radius_m * 1e3) as f32],
        )
        .with_colors([rerun::Color::from_rgb(40, 110, 210)]),
    );
    let direction = |v: [f64; 2]| {
        let n = v[0].hypot(v[1]);
        if n > 0.0 {
            [
                (v[0] / n) as f32 * ARROW_MM,
                (v[1] / n) as f32 * ARROW_MM,
                0.0,
            ]
        } else {
            [0.0; 3]
        }
    };
    let origin = at(0.0);
    let field_mt = command.field_des_t[0].hypot(command.field_des_t[1]) * 1e3;
    let force_mn = command.force_des_n[0].hypot(command.force_des_n[1]) * 1e3;
    let _ = rec.log(
        "rig3d/field",
        &rerun::Arrows3D::from_vectors([direction(command.field_des_t)])
            .with_origins([origin])
            .with_colors([rerun::Color::from_rgb(30, 160, 80)])
            .with_labels([format!("B {field_mt:.1} mT")]),
    );
    let _ = rec.log(
        "rig3d/force",
        &rerun::Arrows3D::from_vectors([direction(command.force_des_n)])
            .with_origins([origin])
            .with_colors([rerun::Color::from_rgb(230, 140, 20)])
            .with_labels([format!("F {force_mn:.3} mN")]),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_run_from_grey_to_red_and_blue_at_the_limit() {
        assert_eq!(
            current_colour(0.0, 10.0),
            rerun::Color::from_rgb(170, 170, 170)
        );
        assert_eq!(
            current_colour(10.0, 10.0),
            rerun::Color::from_rgb(220, 40, 40)
        );
        assert_eq!(
            current_colour(-25.0, 10.0),
            rerun::Color::from_rgb(40, 70, 220)
        );
    }
}
