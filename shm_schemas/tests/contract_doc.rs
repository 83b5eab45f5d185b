//! CONTRACT.md against the Rust layout: the version in its title, every payload's heading
//! (`### Type (N bytes, align A)`), its type name, and each row of its field table (offset,
//! size, field) must be what the compiler lays out, and every field must have its row. A
//! foreign reader works from that page alone, so it must not go stale.

use std::collections::BTreeMap;
use std::mem::{align_of, offset_of, size_of};

use iceoryx2::prelude::ZeroCopySend;
use shm_schemas::*;

/// The byte size of a field, from a projection of the struct onto it.
fn size_of_field<T, F>(_: fn(&T) -> &F) -> usize {
    size_of::<F>()
}

/// A payload as the compiler lays it out.
struct Layout {
    size: usize,
    align: usize,
    type_name: Option<&'static str>,
    /// field → (offset, size)
    fields: BTreeMap<&'static str, (usize, usize)>,
}

macro_rules! layout {
    ($type:ident, $name:expr, [$($field:ident),* $(,)?]) => {
        (
            stringify!($type),
            Layout {
                size: size_of::<$type>(),
                align: align_of::<$type>(),
                type_name: $name,
                fields: BTreeMap::from([$((
                    stringify!($field),
                    (offset_of!($type, $field), size_of_field(|t: &$type| &t.$field)),
                )),*]),
            },
        )
    };
}

fn type_name<T: ZeroCopySend>() -> Option<&'static str> {
    // SAFETY: only reads the type's name.
    Some(unsafe { <T as ZeroCopySend>::type_name() })
}

fn layouts() -> BTreeMap<&'static str, Layout> {
    BTreeMap::from([
        layout!(
            FrameStamp,
            None,
            [seq, incarnation, capture_time_ns, grab_time_ns]
        ),
        layout!(
            FrameHeader,
            type_name::<FrameHeader>(),
            [
                stamp,
                width,
                height,
                stride,
                pixel_format,
                mm_per_px,
                origin_x_mm,
                origin_y_mm
            ]
        ),
        layout!(
            Pose,
            type_name::<Pose>(),
            [
                stamp,
                position_m,
                heading_rad,
                tip_m,
                centroid_m,
                tail_m,
                confidence,
                source,
                valid,
                reserved
            ]
        ),
        layout!(
            FlowEstimate,
            type_name::<FlowEstimate>(),
            [stamp, velocity_mps, speed_mps, zone_flags, valid, reserved]
        ),
        layout!(
            CoilCommand,
            type_name::<CoilCommand>(),
            [
                stamp,
                control_incarnation,
                active_coils,
                mode,
                controller_id,
                reserved,
                currents_a,
                force_des_n,
                field_des_t
            ]
        ),
        layout!(
            CoilStatus,
            type_name::<CoilStatus>(),
            [
                frame_seq,
                applied_currents_a,
                link_state,
                active_coils,
                watchdog_tripped,
                board_state,
                board_flags,
                board_fault,
                reserved,
                thermal_permille,
                frames_sent,
                acks_received,
                rx_errors,
                stale_commands_rejected,
                clamp_events,
                deadline_misses,
                reconnects,
                coil_count_rejected,
                board_rejected
            ]
        ),
        layout!(
            PlantTruth,
            type_name::<PlantTruth>(),
            [
                frame_seq,
                sim_time_ns,
                position_m,
                velocity_mps,
                heading_rad,
                true_flow_mps,
                applied_currents_a,
                magnetic_force_n,
                lockstep_misses,
                active_coils,
                wall_contact,
                reserved
            ]
        ),
        layout!(
            Heartbeat,
            type_name::<Heartbeat>(),
            [
                service,
                pid,
                incarnation,
                cycles,
                deadline_misses,
                wall_time_ns,
                dropped_samples,
                source_faults
            ]
        ),
        layout!(
            OperatorRequest,
            type_name::<OperatorRequest>(),
            [request_id, verb, waypoint_count, waypoints_m]
        ),
        layout!(
            OperatorReply,
            type_name::<OperatorReply>(),
            [request_id, accepted, reserved, state, position_m, target_m, message]
        ),
    ])
}

/// A payload as CONTRACT.md describes it.
#[derive(Debug, Default)]
struct Documented {
    size: usize,
    align: usize,
    type_name: Option<String>,
    fields: BTreeMap<String, (usize, usize)>,
}

fn number(text: &str, what: &str) -> usize {
    text.trim()
        .parse()
        .unwrap_or_else(|e| panic!("CONTRACT.md: {what} {text:?}: {e}"))
}

/// The payload sections of CONTRACT.md: `### Name (N bytes, align A)`, the first
/// `` Type name `...` `` after it, and its `| offset | size | field | ... |` rows.
fn documented(text: &str) -> BTreeMap<String, Documented> {
    let mut sections = BTreeMap::new();
    let mut current: Option<(String, Documented)> = None;
    for line in text.lines() {
        if let Some(heading) = line.strip_prefix("### ") {
            if let Some((name, doc)) = current.take() {
                sections.insert(name, doc);
            }
            let Some((name, rest)) = heading.split_once(" (") else {
                continue;
            };
            let rest = rest.trim_end_matches(')');
            let (size, align) = rest
                .split_once(" bytes, align ")
                .unwrap_or_else(|| panic!("CONTRACT.md: heading {heading:?}"));
            current = Some((
                name.to_owned(),
                Documented {
                    size: number(size, "size"),
                    align: number(align, "align"),
                    ..Documented::default()
                },
            ));
        } else if line.starts_with("## ") {
            if let Some((name, doc)) = current.take() {
                sections.insert(name, doc);
            }
        } else if let Some((_, doc)) = current.as_mut() {
            if let Some(rest) = line.strip_prefix("Type name `") {
                if doc.type_name.is_none() {
                    doc.type_name = rest.split('`').next().map(str::to_owned);
                }
            }
            let cells: Vec<&str> = line.trim().trim_matches('|').split('|').collect();
            if line.starts_with('|') && cells.len() >= 3 && cells[0].trim().parse::<usize>().is_ok()
            {
                let field = cells[2].trim().trim_matches('`').to_owned();
                let at = (number(cells[0], "offset"), number(cells[1], "size"));
                assert!(
                    doc.fields.insert(field.clone(), at).is_none(),
                    "CONTRACT.md: field {field} listed twice"
                );
            }
        }
    }
    if let Some((name, doc)) = current {
        sections.insert(name, doc);
    }
    sections
}

fn contract_md() -> String {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/CONTRACT.md");
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

#[test]
fn the_title_names_the_contract_version() {
    let text = contract_md();
    let title = text.lines().next().expect("a title");
    assert_eq!(
        title,
        format!("# millinav shared-memory contract, version {CONTRACT_VERSION}")
    );
    assert!(text.contains(&format!("`CONTRACT_VERSION` = {CONTRACT_VERSION}.")));
}

#[test]
fn every_payload_is_documented_as_it_is_laid_out() {
    let docs = documented(&contract_md());
    let layouts = layouts();
    let names = |m: Vec<&str>| m.join(", ");
    assert_eq!(
        names(docs.keys().map(String::as_str).collect()),
        names(layouts.keys().copied().collect()),
        "the payload sections of CONTRACT.md"
    );
    for (name, layout) in &layouts {
        let doc = &docs[*name];
        assert_eq!(doc.size, layout.size, "{name}: size in its heading");
        assert_eq!(doc.align, layout.align, "{name}: align in its heading");
        assert_eq!(
            doc.type_name.as_deref(),
            layout.type_name,
            "{name}: its type name"
        );
        // Every byte is a field (the contract has no implicit padding), so the list of fields
        // above is complete.
        let bytes: usize = layout.fields.values().map(|(_, size)| size).sum();
        assert_eq!(bytes, layout.size, "{name}: fields do not cover the struct");
        for (field, at) in &layout.fields {
            assert_eq!(
                doc.fields.get(*field),
                Some(at),
                "{name}.{field}: (offset, size) in CONTRACT.md"
            );
        }
        assert_eq!(
            doc.fields.len(),
            layout.fields.len(),
            "{name}: CONTRACT.md lists fields the struct does not have: {:?}",
            doc.fields.keys().collect::<Vec<_>>()
        );
    }
}

#[test]
fn the_parser_sees_a_stale_size_and_a_moved_field() {
    let text = contract_md();
    let stale = text.replace(
        "### Pose (120 bytes, align 8)",
        "### Pose (112 bytes, align 8)",
    );
    assert_eq!(documented(&stale)["Pose"].size, 112);
    let moved = text.replace("| 48 | 8 | `heading_rad` |", "| 40 | 8 | `heading_rad` |");
    assert_eq!(documented(&moved)["Pose"].fields["heading_rad"], (40, 8));
    assert_eq!(documented(&text)["Pose"].fields["heading_rad"], (48, 8));
}
