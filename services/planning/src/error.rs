//! Why a plan was refused.

#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    #[error("mask is {got} bytes, expected {width}x{height} = {expected}")]
    MaskSize {
        width: u32,
        height: u32,
        expected: usize,
        got: usize,
    },
    #[error("invalid image geometry: {0}")]
    Geometry(String),
    #[error("invalid planner config: {0}")]
    Config(String),
    #[error("{which} point ({x_mm:.2}, {y_mm:.2}) mm lies outside the image")]
    OutsideImage {
        which: &'static str,
        x_mm: f64,
        y_mm: f64,
    },
    #[error("{which} point ({x_mm:.2}, {y_mm:.2}) mm lies outside the canal mask")]
    OutsideCanal {
        which: &'static str,
        x_mm: f64,
        y_mm: f64,
    },
    #[error("no pixel of the canal keeps {clearance_mm:.2} mm from the wall")]
    NoFeasibleCore { clearance_mm: f64 },
    #[error(
        "start and end cannot be connected within the {clearance_mm:.2} mm clearance core \
         (start projected to px {start:?}, end to px {end:?})"
    )]
    NotConnected {
        start: (u32, u32),
        end: (u32, u32),
        clearance_mm: f64,
    },
}
