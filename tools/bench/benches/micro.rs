//! Criterion micro-benchmarks of the compute stages (`cargo bench -p millinav-bench`). The
//! `bench` binary times the same workloads per iteration for median/p99 and the IPC and
//! end-to-end rows, which need processes rather than a closure.

use criterion::{criterion_group, criterion_main, Criterion};
use millinav_bench::workload::Workload;
use millinav_bench::{control, vision};
use millinav_control::controllers::ControllerKind;

fn controllers(c: &mut Criterion) {
    let Ok(workload) = Workload::short() else {
        return;
    };
    for (kind, name) in [
        (ControllerKind::Pid, "pid"),
        (ControllerKind::SmcDob, "smc_dob"),
        (ControllerKind::Mpc, "mpc"),
    ] {
        if let Ok(mut b) = control::ControllerBench::new(kind, &workload) {
            let mut k = 0;
            c.bench_function(&format!("control/{name}/update"), |bench| {
                bench.iter(|| {
                    k += 1;
                    b.step(k)
                })
            });
        }
    }
    if let Ok(a) = control::AllocationBench::new(64, &workload) {
        let mut k = 0;
        c.bench_function("allocation/pinv", |b| {
            b.iter(|| {
                k += 1;
                a.pinv(k)
            })
        });
        c.bench_function("allocation/constrained", |b| {
            b.iter(|| {
                k += 1;
                a.constrained(k)
            })
        });
    }
}

fn localizers(c: &mut Criterion) {
    let Ok(workload) = Workload::short() else {
        return;
    };
    let Ok(scene) = vision::Scene::render(0, &workload) else {
        return;
    };
    let classical = vision::classical(&scene);
    let (w, h) = (scene.width as i32, scene.height as i32);
    let roi = scene.roi(20.0);
    c.bench_function("vision/classical_roi", |b| {
        b.iter(|| {
            classical
                .localize(&scene.rgb, w, h, roi, scene.mm_per_px)
                .is_ok()
        })
    });
    let full = scene.full();
    let mut group = c.benchmark_group("vision_slow");
    group.sample_size(20);
    group.bench_function("classical_full_frame", |b| {
        b.iter(|| {
            classical
                .localize(&scene.rgb, w, h, full, scene.mm_per_px)
                .is_ok()
        })
    });
    group.finish();
    if let Ok(mut unet) = vision::unet(&scene) {
        c.bench_function("vision/unet_roi_localize", |b| {
            b.iter(|| {
                unet.localize(&scene.rgb, scene.width, scene.height, scene.centroid_px)
                    .is_ok()
            })
        });
    }
}

/// The twin's raw camera: the second rig's 1280 × 1024 RGB frame sampled from its canonical
/// render through the lens, every lockstep frame (the plant's largest per-frame cost).
fn raw_view(c: &mut Criterion) {
    let path = fieldmaps::data_root().join("fieldmaps/rigs/vessel8.toml");
    let Ok(rig) = fieldmaps::rigfile::Rig::load(&path) else {
        return;
    };
    let Some(calibration) = rig.camera.calibration else {
        return;
    };
    let view = rig.camera.geometry;
    let Ok(map) = calibration.raw_view_map(&view) else {
        return;
    };
    let (w, h, channels) = (view.width_px as usize, view.height_px as usize, 3);
    let canonical: Vec<u8> = (0..w * h * channels).map(|i| (i % 251) as u8).collect();
    let sampler = map.sampler(w, h, w * channels, channels);
    let mut raw = vec![0u8; map.width * map.height * channels];
    let mut group = c.benchmark_group("plant_slow");
    group.sample_size(20);
    group.bench_function("raw_view_remap", |b| {
        b.iter(|| sampler.remap(&canonical, &mut raw))
    });
    group.finish();
}

criterion_group!(benches, controllers, localizers, raw_view);
criterion_main!(benches);
