"""A foreign reader of millinav's shared-memory contract.

Subscribes to the Pose and CoilCommand services of a live run with nothing but `ctypes` and the
PyPI `iceoryx2==0.10.0` package, and decodes them with structures written from
`shm_schemas/CONTRACT.md` alone (no millinav code). Used by `tests/foreign_reader.rs`; also a
starting point for a lab's own tools.

    python foreign_reader.py --prefix P --root DIR --out decoded.json [--seconds 60]

Writes JSON: {"poses": [...], "commands": [...], "errors": [...]} with every sample received
until both services have gone away (the run ended) or the time is up.
"""

import argparse
import ctypes
import json
import sys
import time

import iceoryx2 as iox2

MAX_COILS = 16


class FrameStamp(ctypes.Structure):
    """CONTRACT.md, "FrameStamp": 32 bytes, alignment 8."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("incarnation", ctypes.c_uint64),
        ("capture_time_ns", ctypes.c_uint64),
        ("grab_time_ns", ctypes.c_uint64),
    ]


class Pose(ctypes.Structure):
    """CONTRACT.md, "Pose": type name millinav::Pose.v4, 120 bytes, alignment 8."""

    _fields_ = [
        ("stamp", FrameStamp),
        ("position_m", ctypes.c_double * 2),
        ("heading_rad", ctypes.c_double),
        ("tip_m", ctypes.c_double * 2),
        ("centroid_m", ctypes.c_double * 2),
        ("tail_m", ctypes.c_double * 2),
        ("confidence", ctypes.c_double),
        ("source", ctypes.c_uint32),
        ("valid", ctypes.c_uint8),
        ("reserved", ctypes.c_uint8 * 3),
    ]

    @staticmethod
    def type_name() -> str:
        return "millinav::Pose.v4"


class CoilCommand(ctypes.Structure):
    """CONTRACT.md, "CoilCommand": type name millinav::CoilCommand.v4, 216 bytes, alignment 8."""

    _fields_ = [
        ("stamp", FrameStamp),
        ("control_incarnation", ctypes.c_uint64),
        ("active_coils", ctypes.c_uint32),
        ("mode", ctypes.c_uint32),
        ("controller_id", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
        ("currents_a", ctypes.c_double * MAX_COILS),
        ("force_des_n", ctypes.c_double * 2),
        ("field_des_t", ctypes.c_double * 2),
    ]

    @staticmethod
    def type_name() -> str:
        return "millinav::CoilCommand.v4"


def check_layouts() -> None:
    """The structures match the sizes and offsets CONTRACT.md gives."""
    expected = {
        FrameStamp: (
            32,
            {"seq": 0, "incarnation": 8, "capture_time_ns": 16, "grab_time_ns": 24},
        ),
        Pose: (
            120,
            {
                "stamp": 0,
                "position_m": 32,
                "heading_rad": 48,
                "tip_m": 56,
                "centroid_m": 72,
                "tail_m": 88,
                "confidence": 104,
                "source": 112,
                "valid": 116,
                "reserved": 117,
            },
        ),
        CoilCommand: (
            216,
            {
                "stamp": 0,
                "control_incarnation": 32,
                "active_coils": 40,
                "mode": 44,
                "controller_id": 48,
                "reserved": 52,
                "currents_a": 56,
                "force_des_n": 184,
                "field_des_t": 200,
            },
        ),
    }
    for struct, (size, offsets) in expected.items():
        assert ctypes.sizeof(struct) == size, (struct.__name__, ctypes.sizeof(struct))
        assert ctypes.alignment(struct) == 8, struct.__name__
        for field, offset in offsets.items():
            got = getattr(struct, field).offset
            assert got == offset, (struct.__name__, field, got, offset)


def stamp(s: FrameStamp) -> dict:
    return {
        "seq": s.seq,
        "incarnation": s.incarnation,
        "capture_time_ns": s.capture_time_ns,
        "grab_time_ns": s.grab_time_ns,
    }


def decode_pose(p: Pose) -> dict:
    return {
        "stamp": stamp(p.stamp),
        "position_m": list(p.position_m),
        "heading_rad": p.heading_rad,
        "confidence": p.confidence,
        "source": p.source,
        # The raw byte: the reader decides (0 = invalid, 1 = valid, anything else = violation).
        "valid": p.valid,
    }


def decode_command(c: CoilCommand) -> dict:
    active = c.active_coils
    return {
        "stamp": stamp(c.stamp),
        "control_incarnation": c.control_incarnation,
        "active_coils": active,
        "mode": c.mode,
        "controller_id": c.controller_id,
        # Only the active coils carry currents; a count above MAX_COILS is a violation.
        "currents_a": list(c.currents_a[: min(active, MAX_COILS)]),
        "inactive_currents_a": list(c.currents_a[min(active, MAX_COILS) :]),
        "force_des_n": list(c.force_des_n),
    }


def iceoryx_config(prefix: str, root: str):
    """The run's iceoryx2 namespace, set as millinav's kit sets it (prefix, root ending in /)."""
    config = iox2.config.default()
    config.global_cfg.prefix = iox2.FileName.new(prefix)
    if not root.endswith("/"):
        root += "/"
    config.global_cfg.root_path = iox2.Path.new(root)
    return config


def open_subscriber(node, name: str, payload, deadline: float):
    """Opens `name` once it exists (the run may still be starting) and subscribes."""
    last_error = None
    while time.monotonic() < deadline:
        try:
            service = (
                node.service_builder(iox2.ServiceName.new(name))
                .publish_subscribe(payload)
                .open()
            )
            return service.subscriber_builder().create()
        except Exception as e:  # DoesNotExist while the run starts; anything else is fatal
            last_error = e
            if "DoesNotExist" not in repr(e) and "DoesNotExist" not in str(type(e)):
                raise
            time.sleep(0.02)
    raise TimeoutError(f"{name} did not appear: {last_error!r}")


def drain(subscriber, payload, decode, out: list) -> int:
    got = 0
    while True:
        sample = subscriber.receive()
        if sample is None:
            return got
        value = payload.from_buffer_copy(
            ctypes.string_at(sample.payload_ptr, ctypes.sizeof(payload))
        )
        sample.delete()
        out.append(decode(value))
        got += 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prefix", required=True)
    parser.add_argument("--root", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument(
        "--idle-seconds",
        type=float,
        default=3.0,
        help="stop after this long without any sample once samples have arrived",
    )
    args = parser.parse_args()

    check_layouts()
    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    node = (
        iox2.NodeBuilder.new()
        .config(iceoryx_config(args.prefix, args.root))
        .create(iox2.ServiceType.Ipc)
    )
    deadline = time.monotonic() + args.seconds
    poses_sub = open_subscriber(node, "millinav/vision/pose", Pose, deadline)
    commands_sub = open_subscriber(node, "millinav/control/command", CoilCommand, deadline)
    print("foreign reader subscribed", file=sys.stderr, flush=True)

    poses, commands = [], []
    last_sample = None
    while time.monotonic() < deadline:
        got = drain(poses_sub, Pose, decode_pose, poses)
        got += drain(commands_sub, CoilCommand, decode_command, commands)
        now = time.monotonic()
        if got:
            last_sample = now
        elif last_sample is not None and now - last_sample > args.idle_seconds:
            break
        time.sleep(0.0005)

    with open(args.out, "w", encoding="utf-8") as f:
        json.dump({"poses": poses, "commands": commands}, f)
    print(
        f"foreign reader: {len(poses)} poses, {len(commands)} commands",
        file=sys.stderr,
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
