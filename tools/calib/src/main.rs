//! `calib`: calibrate a rig's camera and write the result into its rig file.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Parser, Subcommand};
use fieldmaps::rigfile::Rig;
use millinav_calib::registration::read_fiducials;
use millinav_calib::rigwrite::{self, Update};
use millinav_calib::{
    calibrate_intrinsics, read_gray, rectification_maps, rectify, register, Checkerboard,
};
use opencv::core::{Mat, Point, Scalar, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

/// Calibrates a rig's top camera: its lens from checkerboard views (`intrinsics`), its
/// registration to the world plane from fiducials (`homography`), and a check image of the
/// phantom mask over a rectified frame (`check`). With `--write`, results go into the rig file's
/// `[camera.calibration]` table (ROS camera_info names), which the camera service reads.
#[derive(Parser)]
#[command(name = "calib", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Intrinsics and distortion (OpenCV plumb_bob) from images of a printed checkerboard,
    /// with each image's and the total RMS reprojection error. Take 10–20 views, tilted, with
    /// the board reaching into the corners of the image.
    Intrinsics {
        /// Images (files, or folders whose PNG/JPEG/BMP/TIFF files are all used).
        #[arg(required = true)]
        images: Vec<PathBuf>,
        /// Inner corners of the board, COLSxROWS (e.g. 9x6: the corners where four squares
        /// meet, not the squares).
        #[arg(long, value_parser = parse_grid)]
        inner_corners: (i32, i32),
        /// Side of one square, mm.
        #[arg(long)]
        square_mm: f64,
        /// Rig file to write the lens into (with --write).
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Write the result into the rig file's [camera.calibration] (replaces the table; a
        /// registration made with another lens must be redone).
        #[arg(long, requires = "rig")]
        write: bool,
    },
    /// The homography from undistorted image pixels to the world plane, from 4 or more
    /// fiducials (CSV: name,u_px,v_px,x_mm,y_mm — where each appears in a raw frame, and its
    /// world position), with each fiducial's residual in mm. Needs the lens in the rig file.
    Homography {
        #[arg(long)]
        fiducials: PathBuf,
        #[arg(long)]
        rig: PathBuf,
        /// Write the registration into the rig file's [camera.calibration].
        #[arg(long)]
        write: bool,
    },
    /// Writes what a camera of known lens would deliver, to try the other commands without a
    /// camera: 16 checkerboard views (8x5 inner corners, 25 mm squares), the fiducials CSV of
    /// a top camera tilted over the rig's phantom, and a raw frame of the phantom mask.
    Synth {
        /// The rig whose phantom the top camera sees.
        #[arg(long)]
        rig: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
    /// Rectifies a raw frame onto the rig's canonical top view with its calibration and draws
    /// the phantom mask's outline over it: where the outline misses the canal, the
    /// registration is off.
    Check {
        #[arg(long)]
        rig: PathBuf,
        /// A raw frame of the camera (an image file).
        #[arg(long)]
        frame: PathBuf,
        /// The PNG to write.
        #[arg(long)]
        out: PathBuf,
    },
}

fn parse_grid(text: &str) -> Result<(i32, i32), String> {
    let (c, r) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected COLSxROWS such as 9x6, got {text:?}"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<i32>()
            .map_err(|_| format!("expected COLSxROWS such as 9x6, got {text:?}"))
    };
    Ok((parse(c)?, parse(r)?))
}

fn image_files(inputs: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .with_context(|| format!("cannot list {}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension().is_some_and(|e| {
                        ["png", "jpg", "jpeg", "bmp", "tif", "tiff"]
                            .contains(&e.to_string_lossy().to_lowercase().as_str())
                    })
                })
                .collect();
            found.sort();
            anyhow::ensure!(
                !found.is_empty(),
                "{}: no images in this folder",
                input.display()
            );
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    Ok(files)
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Intrinsics {
            images,
            inner_corners,
            square_mm,
            rig,
            write,
        } => intrinsics(&images, inner_corners, square_mm, rig.as_deref(), write),
        Command::Homography {
            fiducials,
            rig,
            write,
        } => homography(&fiducials, &rig, write),
        Command::Check { rig, frame, out } => check(&rig, &frame, &out),
        Command::Synth { rig, out } => synth(&rig, &out),
    }
}

fn intrinsics(
    inputs: &[PathBuf],
    (cols, rows): (i32, i32),
    square_mm: f64,
    rig: Option<&Path>,
    write: bool,
) -> anyhow::Result<()> {
    let board = Checkerboard {
        cols,
        rows,
        square_m: square_mm * 1e-3,
    };
    board.validate()?;
    let files = image_files(inputs)?;
    let mut views = Vec::with_capacity(files.len());
    for f in &files {
        views.push((f.clone(), read_gray(f)?));
    }
    let bar = indicatif::ProgressBar::new(views.len() as u64).with_message("finding the board");
    let lens = calibrate_intrinsics(&views, &board, |n| bar.set_position(n as u64))?;
    bar.finish_and_clear();
    println!("{:<40} reprojection RMS px", "image");
    for (path, rms) in &lens.per_image {
        match rms {
            Some(rms) => println!("{:<40} {rms:.3}", path.display()),
            None => println!("{:<40} board not found (not used)", path.display()),
        }
    }
    let k = &lens.camera_matrix;
    println!(
        "{} of {} views used; total RMS {:.3} px; {}x{} px; fx {:.2} fy {:.2} cx {:.2} cy {:.2}; \
         k1 {:.5} k2 {:.5} p1 {:.5} p2 {:.5} k3 {:.5}",
        lens.per_image.iter().filter(|(_, r)| r.is_some()).count(),
        lens.per_image.len(),
        lens.rms_px,
        lens.image_width,
        lens.image_height,
        k[0],
        k[4],
        k[2],
        k[5],
        lens.distortion[0],
        lens.distortion[1],
        lens.distortion[2],
        lens.distortion[3],
        lens.distortion[4]
    );
    if write {
        let rig = rig.context("--write needs --rig")?;
        rigwrite::write(rig, Update::Intrinsics(&lens))?;
        println!("written to {} [camera.calibration]", rig.display());
    }
    Ok(())
}

fn homography(fiducials: &Path, rig_path: &Path, write: bool) -> anyhow::Result<()> {
    let rig = Rig::load(rig_path)?;
    let calibration = rig.camera.calibration.with_context(|| {
        format!(
            "{}: camera.calibration: no lens yet; run `calib intrinsics --rig {} --write` first",
            rig_path.display(),
            rig_path.display()
        )
    })?;
    let points = read_fiducials(fiducials)?;
    let registration = register(&calibration, &points)
        .with_context(|| format!("fiducials {}", fiducials.display()))?;
    println!("{:<20} residual mm", "fiducial");
    for (name, error) in &registration.residuals_mm {
        println!("{name:<20} {error:.3}");
    }
    println!(
        "{} fiducials; RMS residual {:.3} mm (with exactly 4 the fit is exact: add more to see \
         the error)",
        points.len(),
        registration.rms_mm
    );
    if write {
        rigwrite::write(rig_path, Update::Registration(&registration))?;
        println!("written to {} [camera.calibration]", rig_path.display());
    }
    Ok(())
}

fn check(rig_path: &Path, frame_path: &Path, out: &Path) -> anyhow::Result<()> {
    let rig = Rig::load(rig_path)?;
    let calibration = rig.camera.calibration.with_context(|| {
        format!(
            "{}: camera.calibration: the camera is not calibrated",
            rig_path.display()
        )
    })?;
    let frame = imgcodecs::imread(frame_path, imgcodecs::IMREAD_COLOR)?;
    anyhow::ensure!(
        !frame.empty(),
        "{}: not a readable image",
        frame_path.display()
    );
    let size = frame.size()?;
    anyhow::ensure!(
        size.width as u32 == calibration.image_width
            && size.height as u32 == calibration.image_height,
        "{}: the frame is {}x{} px, the calibrated camera's {}x{} px",
        frame_path.display(),
        size.width,
        size.height,
        calibration.image_width,
        calibration.image_height
    );
    let view = rig.camera.geometry;
    let maps = rectification_maps(&calibration, &view)?;
    let mut rectified = rectify(&frame, &maps)?;
    // The mask on the canonical view's grid, and its outline.
    let mask_pixels = rig.phantom.mask.resampled(&view);
    let mask =
        Mat::new_rows_cols_with_data(view.height_px as i32, view.width_px as i32, &mask_pixels)?
            .try_clone()?;
    let mut binary = Mat::default();
    imgproc::threshold(&mask, &mut binary, 0.0, 255.0, imgproc::THRESH_BINARY)?;
    let mut contours = Vector::<Vector<Point>>::new();
    imgproc::find_contours_def(
        &binary,
        &mut contours,
        imgproc::RETR_LIST,
        imgproc::CHAIN_APPROX_NONE,
    )?;
    imgproc::draw_contours(
        &mut rectified,
        &contours,
        -1,
        Scalar::new(0.0, 255.0, 0.0, 0.0),
        2,
        imgproc::LINE_8,
        &opencv::core::no_array(),
        i32::MAX,
        Point::new(0, 0),
    )?;
    anyhow::ensure!(
        imgcodecs::imwrite_def(out, &rectified)?,
        "{}: cannot write the PNG",
        out.display()
    );
    println!(
        "{}: {} rectified onto the {}x{} px top view with the mask outline ({} contours)",
        out.display(),
        frame_path.display(),
        view.width_px,
        view.height_px,
        contours.len()
    );
    Ok(())
}

fn synth(rig_path: &Path, out: &Path) -> anyhow::Result<()> {
    use millinav_calib::synthetic::{
        calibration_view, project, render_plane, top_camera_pose, CALIBRATION_POSES, DEMO_BOARD,
        DEMO_LENS,
    };
    let rig = Rig::load(rig_path)?;
    let views = out.join("views");
    std::fs::create_dir_all(&views)
        .with_context(|| format!("cannot create {}", views.display()))?;
    let bar =
        indicatif::ProgressBar::new(CALIBRATION_POSES.len() as u64 + 1).with_message("rendering");
    for k in 0..CALIBRATION_POSES.len() {
        let image = calibration_view(&DEMO_LENS, &DEMO_BOARD, k)?;
        let path = views.join(format!("view{k:02}.png"));
        anyhow::ensure!(
            imgcodecs::imwrite_def(&path, &image)?,
            "cannot write {}",
            path.display()
        );
        bar.inc(1);
    }
    // A top camera above the view's centre, high enough that the view fills about half of the
    // image's height, tilted by a few degrees.
    let g = rig.camera.geometry;
    let (w_m, h_m) = (
        f64::from(g.width_px) * g.mm_per_px * 1e-3,
        f64::from(g.height_px) * g.mm_per_px * 1e-3,
    );
    let centre = (
        g.origin_x_mm * 1e-3 + w_m / 2.0,
        g.origin_y_mm * 1e-3 - h_m / 2.0,
    );
    let height = h_m.max(w_m) * DEMO_LENS.camera_matrix[4] / (0.5 * f64::from(DEMO_LENS.height));
    let pose = top_camera_pose([centre.0, centre.1, height], (0.10, -0.07, 0.04));
    let mask = &rig.phantom.mask;
    let frame = render_plane(&DEMO_LENS, &pose, 2, 2.0, 99, |x, y| {
        if mask.contains(&nalgebra::Vector2::new(x, y)) {
            225.0
        } else {
            45.0
        }
    })?;
    let frame_path = out.join("frame.png");
    anyhow::ensure!(
        imgcodecs::imwrite_def(&frame_path, &frame)?,
        "cannot write {}",
        frame_path.display()
    );
    bar.inc(1);
    bar.finish_and_clear();
    // Nine fiducials over the view (a 3x3 grid at 10 % and 90 % of it and its middle).
    let mut csv = String::from("name,u_px,v_px,x_mm,y_mm\n");
    let mut world = Vec::new();
    for (j, fy) in [0.1, 0.5, 0.9].iter().enumerate() {
        for (i, fx) in [0.1, 0.5, 0.9].iter().enumerate() {
            let x = g.origin_x_mm + fx * w_m * 1e3;
            let y = g.origin_y_mm - fy * h_m * 1e3;
            world.push((format!("f{j}{i}"), x, y));
        }
    }
    let points: Vec<[f64; 3]> = world
        .iter()
        .map(|(_, x, y)| [x * 1e-3, y * 1e-3, 0.0])
        .collect();
    for ((name, x, y), (u, v)) in world.iter().zip(project(&DEMO_LENS, &pose, &points)?) {
        csv.push_str(&format!("{name},{u:.3},{v:.3},{x:.3},{y:.3}\n"));
    }
    let csv_path = out.join("fiducials.csv");
    std::fs::write(&csv_path, csv)
        .with_context(|| format!("cannot write {}", csv_path.display()))?;
    println!(
        "{}: {} checkerboard views (8x5 inner corners, 25 mm squares) in views/, frame.png (the \
         phantom through a tilted {}x{} px camera {:.0} mm up) and fiducials.csv",
        out.display(),
        CALIBRATION_POSES.len(),
        DEMO_LENS.width,
        DEMO_LENS.height,
        height * 1e3
    );
    Ok(())
}
