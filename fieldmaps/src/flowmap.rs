//! Steady in-plane flow maps (Vx, Vy) at the control plane, on a regular grid, with bilinear
//! lookup. The controller's flow estimate and the plant's true flow both start from a map.
//!
//! File format (`.flow.csv`, open and plain): a header of `# key = value` lines, then a CSV
//! table `x_mm,y_mm,vx_mps,vy_mps` with one row per grid node, row-major, y outer loop.
//! Required header keys: `format = millinav-flow-v1`, `nx`, `ny`, `x0_mm`, `y0_mm`, `spacing_mm`.

use std::path::{Path, PathBuf};

use nalgebra::Vector2;

#[derive(Debug, thiserror::Error)]
pub enum FlowMapError {
    #[error("cannot read flow map {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("flow map {path}: {message}")]
    Format { path: PathBuf, message: String },
}

/// A steady 2D velocity field on a regular grid (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct FlowMap {
    pub nx: usize,
    pub ny: usize,
    /// Position of node (0, 0), m.
    pub origin_m: Vector2<f64>,
    pub spacing_m: f64,
    /// Row-major, `j * nx + i` is node (x0 + i·h, y0 + j·h).
    pub velocity_mps: Vec<Vector2<f64>>,
    /// Peak speed in the heart chamber (the optional `chamber_peak_mps` header key): the
    /// condition's "peak velocity" in the paper's sense. `peak_speed()` is usually set by the
    /// narrow outlet funnel instead, 1.3–1.6x higher.
    pub chamber_peak_mps: Option<f64>,
}

impl FlowMap {
    /// Quiescent fluid: a map that is zero everywhere.
    pub fn zero() -> Self {
        Self {
            nx: 2,
            ny: 2,
            origin_m: Vector2::new(-0.05, -0.05),
            spacing_m: 0.1,
            velocity_mps: vec![Vector2::zeros(); 4],
            chamber_peak_mps: None,
        }
    }

    /// True if `p` lies within the grid.
    pub fn covers(&self, p: &Vector2<f64>) -> bool {
        let u = (p - self.origin_m) / self.spacing_m;
        u.x >= 0.0 && u.y >= 0.0 && u.x <= (self.nx - 1) as f64 && u.y <= (self.ny - 1) as f64
    }

    /// Bilinear interpolation; outside the grid the nearest edge value is used.
    pub fn sample(&self, p: &Vector2<f64>) -> Vector2<f64> {
        if !(p.x.is_finite() && p.y.is_finite()) {
            return Vector2::zeros();
        }
        let u = (p - self.origin_m) / self.spacing_m;
        let fx = u.x.clamp(0.0, (self.nx - 1) as f64);
        let fy = u.y.clamp(0.0, (self.ny - 1) as f64);
        let i0 = (fx.floor() as usize).min(self.nx - 2);
        let j0 = (fy.floor() as usize).min(self.ny - 2);
        let tx = fx - i0 as f64;
        let ty = fy - j0 as f64;
        let at = |i: usize, j: usize| self.velocity_mps[j * self.nx + i];
        at(i0, j0) * ((1.0 - tx) * (1.0 - ty))
            + at(i0 + 1, j0) * (tx * (1.0 - ty))
            + at(i0, j0 + 1) * ((1.0 - tx) * ty)
            + at(i0 + 1, j0 + 1) * (tx * ty)
    }

    pub fn peak_speed(&self) -> f64 {
        self.velocity_mps
            .iter()
            .map(|v| v.norm())
            .fold(0.0, f64::max)
    }

    /// The speed that characterises the condition: the chamber peak when the map says it,
    /// else the peak over the whole grid.
    pub fn condition_peak_speed(&self) -> f64 {
        self.chamber_peak_mps
            .filter(|v| v.is_finite() && *v >= 0.0)
            .unwrap_or_else(|| self.peak_speed())
    }

    /// Multiplies every velocity by `factor` (e.g. to scale a map to a flow condition).
    pub fn scaled(&self, factor: f64) -> Self {
        let mut out = self.clone();
        out.velocity_mps.iter_mut().for_each(|v| *v *= factor);
        out.chamber_peak_mps = out.chamber_peak_mps.map(|v| v * factor.abs());
        out
    }

    pub fn load(path: &Path) -> Result<Self, FlowMapError> {
        let text = std::fs::read_to_string(path).map_err(|source| FlowMapError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text).map_err(|message| FlowMapError::Format {
            path: path.to_owned(),
            message,
        })
    }

    pub fn save(&self, path: &Path) -> Result<(), FlowMapError> {
        std::fs::write(path, self.to_text()).map_err(|source| FlowMapError::Io {
            path: path.to_owned(),
            source,
        })
    }

    pub fn to_text(&self) -> String {
        let mut out = String::new();
        out.push_str("# format = millinav-flow-v1\n");
        out.push_str(&format!("# nx = {}\n# ny = {}\n", self.nx, self.ny));
        out.push_str(&format!(
            "# x0_mm = {}\n# y0_mm = {}\n# spacing_mm = {}\n",
            self.origin_m.x * 1e3,
            self.origin_m.y * 1e3,
            self.spacing_m * 1e3
        ));
        if let Some(peak) = self.chamber_peak_mps {
            out.push_str(&format!("# chamber_peak_mps = {peak}\n"));
        }
        out.push_str("x_mm,y_mm,vx_mps,vy_mps\n");
        for j in 0..self.ny {
            for i in 0..self.nx {
                let v = self.velocity_mps[j * self.nx + i];
                let x = (self.origin_m.x + i as f64 * self.spacing_m) * 1e3;
                let y = (self.origin_m.y + j as f64 * self.spacing_m) * 1e3;
                out.push_str(&format!("{x:.4},{y:.4},{:.6e},{:.6e}\n", v.x, v.y));
            }
        }
        out
    }

    /// Parses the text format; the error says what is wrong and where.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut header = std::collections::HashMap::new();
        let mut rows = Vec::new();
        let mut saw_columns = false;
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            if let Some(kv) = line.strip_prefix('#') {
                if let Some((k, v)) = kv.split_once('=') {
                    header.insert(k.trim().to_string(), v.trim().to_string());
                }
                continue;
            }
            if !saw_columns {
                if line != "x_mm,y_mm,vx_mps,vy_mps" {
                    return Err(format!(
                        "line {}: expected column header x_mm,y_mm,vx_mps,vy_mps",
                        n + 1
                    ));
                }
                saw_columns = true;
                continue;
            }
            let fields: Vec<&str> = line.split(',').collect();
            if fields.len() != 4 {
                return Err(format!(
                    "line {}: expected 4 fields, got {}",
                    n + 1,
                    fields.len()
                ));
            }
            let mut values = [0.0f64; 4];
            for (v, f) in values.iter_mut().zip(&fields) {
                *v = f
                    .trim()
                    .parse()
                    .map_err(|_| format!("line {}: {f:?} is not a number", n + 1))?;
                if !v.is_finite() {
                    return Err(format!("line {}: non-finite value {f:?}", n + 1));
                }
            }
            rows.push(Vector2::new(values[2], values[3]));
        }
        if header.get("format").map(String::as_str) != Some("millinav-flow-v1") {
            return Err("missing or wrong '# format = millinav-flow-v1' header".into());
        }
        let get = |key: &str| -> Result<f64, String> {
            header
                .get(key)
                .ok_or(format!("missing header key {key}"))?
                .parse::<f64>()
                .map_err(|_| format!("header key {key} is not a number"))
        };
        let nx = get("nx")? as usize;
        let ny = get("ny")? as usize;
        let spacing_mm = get("spacing_mm")?;
        if nx < 2 || ny < 2 {
            return Err(format!("grid must be at least 2x2, got {nx}x{ny}"));
        }
        if !(spacing_mm.is_finite() && spacing_mm > 0.0) {
            return Err(format!("spacing_mm must be > 0, got {spacing_mm}"));
        }
        if rows.len() != nx * ny {
            return Err(format!(
                "truncated or oversized: header says {nx}x{ny} = {} nodes, file has {}",
                nx * ny,
                rows.len()
            ));
        }
        Ok(Self {
            nx,
            ny,
            origin_m: Vector2::new(get("x0_mm")? * 1e-3, get("y0_mm")? * 1e-3),
            spacing_m: spacing_mm * 1e-3,
            velocity_mps: rows,
            chamber_peak_mps: match header.get("chamber_peak_mps") {
                None => None,
                Some(v) => Some(
                    v.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite() && *v >= 0.0)
                        .ok_or("header key chamber_peak_mps is not a non-negative number")?,
                ),
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp() -> FlowMap {
        let (nx, ny) = (5, 4);
        let mut v = Vec::new();
        for j in 0..ny {
            for i in 0..nx {
                v.push(Vector2::new(i as f64 * 0.01, j as f64 * -0.02));
            }
        }
        FlowMap {
            nx,
            ny,
            origin_m: Vector2::new(-0.002, 0.001),
            spacing_m: 0.001,
            velocity_mps: v,
            chamber_peak_mps: None,
        }
    }

    #[test]
    fn bilinear_is_exact_on_linear_fields() {
        let map = ramp();
        let p = Vector2::new(-0.002 + 0.0025, 0.001 + 0.0013);
        let v = map.sample(&p);
        assert!(
            (v.x - 0.025).abs() < 1e-12 && (v.y + 0.026).abs() < 1e-12,
            "{v}"
        );
        assert!(map.covers(&p));
        assert!(!map.covers(&Vector2::new(1.0, 0.0)));
        assert_eq!(map.sample(&Vector2::new(f64::NAN, 0.0)), Vector2::zeros());
    }

    #[test]
    fn text_round_trip_and_clear_errors() {
        let map = ramp();
        let parsed = FlowMap::parse(&map.to_text()).unwrap();
        assert_eq!(parsed.nx, map.nx);
        for (a, b) in parsed.velocity_mps.iter().zip(&map.velocity_mps) {
            assert!((a - b).norm() < 1e-9);
        }
        let text = map.to_text();
        let truncated: String = text.lines().take(10).collect::<Vec<_>>().join("\n");
        let err = FlowMap::parse(&truncated).unwrap_err();
        assert!(err.contains("truncated"), "{err}");
        let mislabelled = text.replace("millinav-flow-v1", "something-else");
        assert!(FlowMap::parse(&mislabelled).unwrap_err().contains("format"));
        // A non-number in the first data row: the error names the line and the value.
        let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
        let first_row = lines
            .iter()
            .position(|l| l == "x_mm,y_mm,vx_mps,vy_mps")
            .expect("column header")
            + 1;
        let mut fields: Vec<&str> = lines[first_row].split(',').collect();
        fields[2] = "abc";
        lines[first_row] = fields.join(",");
        let err = FlowMap::parse(&lines.join("\n")).unwrap_err();
        assert!(
            err.contains(&format!("line {}", first_row + 1))
                && err.contains("\"abc\" is not a number"),
            "{err}"
        );
    }

    #[test]
    fn chamber_peak_round_trips_scales_and_rejects_garbage() {
        let mut map = ramp();
        assert_eq!(map.condition_peak_speed(), map.peak_speed());
        map.chamber_peak_mps = Some(0.07);
        let parsed = FlowMap::parse(&map.to_text()).unwrap();
        assert_eq!(parsed.chamber_peak_mps, Some(0.07));
        assert!((parsed.scaled(2.0).condition_peak_speed() - 0.14).abs() < 1e-12);
        let bad = map
            .to_text()
            .replace("# chamber_peak_mps = 0.07", "# chamber_peak_mps = fast");
        let err = FlowMap::parse(&bad).unwrap_err();
        assert!(err.contains("chamber_peak_mps"), "{err}");
    }
}
