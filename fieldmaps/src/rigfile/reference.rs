//! `[[electromagnet.reference_fields]]`: fields the rig's coils are known to make (a gaussmeter
//! reading, an FEA result), which the coil model should reproduce. `millinav maps coils`
//! reports model against reference; a lab uses them to check its turns and its maps.

use nalgebra::{Unit, Vector3};

use super::build::{finite, fmt_vec, positive, Ctx};
use super::schema::ReferenceFieldSection;
use super::{RigCoil, RigFileError};
use crate::coils::ReferenceField;

pub(super) fn build(
    ctx: &Ctx<'_>,
    sections: &[ReferenceFieldSection],
    coils: &[RigCoil],
) -> Result<Vec<ReferenceField>, RigFileError> {
    sections
        .iter()
        .enumerate()
        .map(|(i, section)| {
            build_one(
                ctx,
                &format!("electromagnet.reference_fields[{i}]"),
                section,
                coils,
            )
        })
        .collect()
}

fn build_one(
    ctx: &Ctx<'_>,
    at: &str,
    r: &ReferenceFieldSection,
    coils: &[RigCoil],
) -> Result<ReferenceField, RigFileError> {
    let key = |k: &str| format!("{at}.{k}");
    let currents_a = currents(ctx, at, r, coils)?;
    if !finite(&r.point_mm) {
        return Err(ctx.err(
            key("point_mm"),
            format!("must be finite, got {}", fmt_vec(&r.point_mm)),
        ));
    }
    let direction = match (
        finite(&r.direction),
        Vector3::from(r.direction).try_normalize(1e-12),
    ) {
        (true, Some(unit)) => Unit::new_unchecked(unit),
        _ => {
            return Err(ctx.err(
                key("direction"),
                format!(
                    "must be a finite non-zero vector, got {}",
                    fmt_vec(&r.direction)
                ),
            ))
        }
    };
    if !positive(r.field_mt) {
        return Err(ctx.err(key("field_mt"), format!("must be > 0, got {}", r.field_mt)));
    }
    if let Some(g) = r.gradient_mt_per_cm {
        if !g.is_finite() {
            return Err(ctx.err(
                key("gradient_mt_per_cm"),
                format!("must be finite, got {g}"),
            ));
        }
    }
    Ok(ReferenceField {
        source: r.source.clone(),
        currents_a,
        point_m: Vector3::from(r.point_mm) * 1e-3,
        direction,
        field_t: r.field_mt * 1e-3,
        // mT/cm → T/m: 1e-3 / 1e-2.
        gradient_t_per_m: r.gradient_mt_per_cm.map(|g| g * 0.1),
    })
}

/// (coil index, current) of every coil the reference names: its `current_a`, or the current
/// that dissipates `power_w` in that coil's resistance.
fn currents(
    ctx: &Ctx<'_>,
    at: &str,
    r: &ReferenceFieldSection,
    coils: &[RigCoil],
) -> Result<Vec<(usize, f64)>, RigFileError> {
    let key = |k: &str| format!("{at}.{k}");
    if r.coils.is_empty() {
        return Err(ctx.err(key("coils"), "must name at least one coil"));
    }
    let current_of = |coil: &RigCoil| -> Result<f64, RigFileError> {
        match (r.current_a, r.power_w) {
            (Some(i), None) if i.is_finite() && i != 0.0 => Ok(i),
            (Some(i), None) => Err(ctx.err(
                key("current_a"),
                format!("must be finite and not 0, got {i}"),
            )),
            (None, Some(p)) if positive(p) => Ok((p / coil.resistance_ohm).sqrt()),
            (None, Some(p)) => Err(ctx.err(key("power_w"), format!("must be > 0, got {p}"))),
            _ => Err(ctx.err(at, "give exactly one of `current_a` and `power_w`")),
        }
    };
    let mut driven: Vec<(usize, f64)> = Vec::with_capacity(r.coils.len());
    for (k, name) in r.coils.iter().enumerate() {
        let Some(id) = coils.iter().position(|c| &c.name == name) else {
            return Err(ctx.err(
                format!("{at}.coils[{k}]"),
                format!("no coil named {name:?} in [[coils]]"),
            ));
        };
        if driven.iter().any(|&(d, _)| d == id) {
            return Err(ctx.err(
                format!("{at}.coils[{k}]"),
                format!("{name:?} is listed twice"),
            ));
        }
        driven.push((id, current_of(&coils[id])?));
    }
    Ok(driven)
}
