//! The canal mask the planner searches, and a geometry for a bare mask image.

use fieldmaps::phantom::{rasterize, ImageGeometry, Phantom};

use crate::PlanError;

/// Binary canal mask, row-major, non-zero = canal.
#[derive(Debug, Clone, PartialEq)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Mask {
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self, PlanError> {
        let expected = width as usize * height as usize;
        if width == 0 || height == 0 || data.len() != expected {
            return Err(PlanError::MaskSize {
                width,
                height,
                expected,
                got: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// The fieldmaps phantom rasterized on `geom`.
    pub fn from_phantom(phantom: &Phantom, geom: &ImageGeometry) -> Result<Self, PlanError> {
        geom.validate()
            .map_err(|e| PlanError::Geometry(e.to_string()))?;
        Self::new(geom.width_px, geom.height_px, rasterize(phantom, geom))
    }

    fn index(&self, col: u32, row: u32) -> usize {
        row as usize * self.width as usize + col as usize
    }

    pub fn is_canal(&self, col: u32, row: u32) -> bool {
        col < self.width && row < self.height && self.data[self.index(col, row)] != 0
    }
}

/// Geometry for a mask of `width × height` px at `mm_per_px`, its field of view centred on the
/// origin.
pub fn geometry_for(width: u32, height: u32, mm_per_px: f64) -> ImageGeometry {
    ImageGeometry {
        width_px: width,
        height_px: height,
        mm_per_px,
        origin_x_mm: -0.5 * f64::from(width) * mm_per_px,
        origin_y_mm: 0.5 * f64::from(height) * mm_per_px,
    }
}
