//! A peer built against another contract version must fail to connect with a clear error, not
//! misread the bytes: a service created with a payload of the same layout but another type name
//! (here the same `Pose` under its version-1 name) is refused by the kit's ports with
//! `KitError::ContractMismatch`, naming the service and the contract version.

mod common;

use common::Isolated;
use millinav_kit::iceoryx2::prelude::*;
use millinav_kit::ports::{FrameInbox, Inbox, Outbox};
use millinav_kit::KitError;
use shm_schemas::{services, Flag, FrameStamp, Pose, CONTRACT_VERSION};

/// `Pose` byte for byte, as an older build named it.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("millinav::Pose.v1")]
struct PoseV1 {
    stamp: FrameStamp,
    position_m: [f64; 2],
    heading_rad: f64,
    tip_m: [f64; 2],
    centroid_m: [f64; 2],
    tail_m: [f64; 2],
    confidence: f64,
    source: u32,
    valid: Flag,
    reserved: [u8; 3],
}

const _: () = assert!(size_of::<PoseV1>() == size_of::<Pose>());

/// A header of the Frame service's size under another name.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("millinav::FrameHeader.v1")]
struct FrameHeaderV1 {
    bytes: [u64; 8],
}

fn assert_mismatch(error: KitError, service: &str, expected_type: &str) {
    let text = error.to_string();
    assert!(
        matches!(&error, KitError::ContractMismatch { service: s, .. } if s == service),
        "not a contract mismatch: {text}"
    );
    assert!(text.contains(service), "{text}");
    assert!(text.contains("another contract version"), "{text}");
    assert!(text.contains(expected_type), "{text}");
    assert!(
        text.contains(&format!("contract v{CONTRACT_VERSION}")),
        "{text}"
    );
}

#[test]
fn ports_refuse_a_service_of_another_contract_version() {
    let world = Isolated::new();
    let node = world.node();
    let old = node
        .service_builder(&ServiceName::new(services::POSE).unwrap())
        .publish_subscribe::<PoseV1>()
        .create()
        .unwrap();
    let _old_publisher = old.publisher_builder().create().unwrap();

    let error =
        Inbox::<Pose>::new(&node, services::POSE).expect_err("an Inbox<Pose> opened a v1 service");
    assert_mismatch(error, services::POSE, "millinav::Pose.v4");
    let error = Outbox::<Pose>::new(&node, services::POSE)
        .err()
        .expect("an Outbox<Pose> opened a v1 service");
    assert_mismatch(error, services::POSE, "millinav::Pose.v4");
}

#[test]
fn same_version_connects_and_delivers() {
    let world = Isolated::new();
    let node = world.node();
    let outbox = Outbox::<Pose>::new(&node, services::POSE).unwrap();
    let inbox = Inbox::<Pose>::new(&node, services::POSE).unwrap();
    outbox.update_connections();
    let pose = Pose {
        stamp: FrameStamp::new(3, 1, 30),
        valid: Flag::TRUE,
        ..Default::default()
    };
    outbox.send(pose).unwrap();
    assert_eq!(inbox.receive_all().unwrap(), vec![pose]);
}

#[test]
fn frame_inbox_refuses_a_frame_header_of_another_version() {
    let world = Isolated::new();
    let node = world.node();
    let _old = node
        .service_builder(&ServiceName::new(services::FRAME).unwrap())
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeaderV1>()
        .create()
        .unwrap();
    let error = FrameInbox::new(&node).expect_err("a FrameInbox opened a v1 frame service");
    assert_mismatch(error, services::FRAME, "millinav::FrameHeader.v4");
}
