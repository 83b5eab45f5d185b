//! Every scenario key the experiments read or write, in one table that a test resolves against
//! the services' config types: a renamed or misspelt field fails
//! `every_key_resolves_against_the_config_types` at `cargo test`, not as a silent default in a
//! matrix's report.

use anyhow::Context;

/// The TOML type a key holds, with a value it may take (the check writes it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kind {
    Float(f64),
    Integer(i64),
    Bool(bool),
    Text(&'static str),
    /// A table whose fields all have defaults.
    Table,
}

/// A key in a scenario: its tables, then its name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Key {
    pub path: &'static [&'static str],
    pub kind: Kind,
}

impl Key {
    const fn new(path: &'static [&'static str], kind: Kind) -> Self {
        Self { path, kind }
    }

    /// `plant.camera.latency_frames`, as users write it in `--set`.
    pub fn dotted(&self) -> String {
        self.path.join(".")
    }

    /// The value at the key, when the document has it.
    pub fn get<'a>(&self, doc: &'a toml::Table) -> Option<&'a toml::Value> {
        let (key, tables) = self.path.split_last()?;
        let mut table = doc;
        for name in tables {
            table = table.get(*name)?.as_table()?;
        }
        table.get(*key)
    }

    /// The value at the key as a number (TOML integers too).
    pub fn number(&self, doc: &toml::Table) -> Option<f64> {
        let value = self.get(doc)?;
        value
            .as_float()
            .or_else(|| value.as_integer().map(|i| i as f64))
    }

    /// Sets the key, creating its tables on the way.
    pub fn set(&self, doc: &mut toml::Table, value: impl Into<toml::Value>) -> anyhow::Result<()> {
        crate::set_in_table(doc, self.path, value.into())
            .with_context(|| format!("setting {}", self.dotted()))
    }

    /// Sets the key where the document does not give it.
    pub fn set_if_absent(
        &self,
        doc: &mut toml::Table,
        value: impl Into<toml::Value>,
    ) -> anyhow::Result<()> {
        if self.get(doc).is_none() {
            self.set(doc, value)?;
        }
        Ok(())
    }

    /// Removes the key; its tables stay (created if missing), so the document keeps its shape.
    pub fn remove(&self, doc: &mut toml::Table) -> anyhow::Result<()> {
        let (key, tables) = self.path.split_last().context("empty key path")?;
        crate::table_at(doc, tables)?.remove(*key);
        Ok(())
    }
}

pub const SEED: Key = Key::new(&["run", "seed"], Kind::Integer(7));
pub const DURATION_S: Key = Key::new(&["run", "duration_s"], Kind::Float(2.0));
pub const FRAME_PERIOD_MS: Key = Key::new(&["run", "frame_period_ms"], Kind::Float(20.0));
pub const VISCOSITY_CP: Key = Key::new(&["fluid", "viscosity_cp"], Kind::Float(4.3));
pub const FLOW_MAP: Key = Key::new(&["flow", "map"], Kind::Text("maps/flow.npz"));

pub const CONTROLLER: Key = Key::new(&["control", "controller"], Kind::Text("pid"));
pub const CONSTRAINED_ALLOCATION: Key =
    Key::new(&["control", "constrained_allocation"], Kind::Bool(true));
pub const USE_ALL_COILS: Key = Key::new(&["control", "use_all_coils"], Kind::Bool(true));
pub const FIELD_HEADING_TURN_DEG: Key =
    Key::new(&["control", "field_heading_turn_deg"], Kind::Float(45.0));
pub const FIELD_FOLLOWS_FORCE: Key =
    Key::new(&["control", "field_follows_force"], Kind::Bool(true));
pub const GAIN_ESTIMATION_ENABLED: Key =
    Key::new(&["control", "gain_estimation", "enabled"], Kind::Bool(true));
pub const SMC_K4_N: Key = Key::new(&["control", "smc", "k4_n"], Kind::Float(1e-4));
pub const SMC_ETA_S: Key = Key::new(&["control", "smc", "eta_s"], Kind::Float(0.1));
pub const SMC_PHI_M: Key = Key::new(&["control", "smc", "phi_m"], Kind::Float(1e-3));
pub const SMC_FLOW_K4_N: Key = Key::new(&["control", "smc", "flow_k4_n"], Kind::Float(1e-4));
pub const SMC_FLOW_ETA_S: Key = Key::new(&["control", "smc", "flow_eta_s"], Kind::Float(0.1));
pub const SMC_FLOW_PHI_M: Key = Key::new(&["control", "smc", "flow_phi_m"], Kind::Float(1e-3));
pub const VELOCITY_ESTIMATE: Key =
    Key::new(&["control", "velocity_estimate"], Kind::Text("observer"));
pub const MAX_CURRENT_SLEW: Key =
    Key::new(&["control", "max_current_slew_a_per_s"], Kind::Float(100.0));
pub const SLEW_YIELD: Key = Key::new(&["control", "slew_yield"], Kind::Table);
pub const SLEW_YIELD_SHORTFALL: Key = Key::new(
    &["control", "slew_yield", "shortfall_fraction"],
    Kind::Float(0.5),
);
pub const SLEW_YIELD_MAX_SLEW: Key = Key::new(
    &["control", "slew_yield", "max_current_slew_a_per_s"],
    Kind::Float(400.0),
);
pub const LATENCY_COMPENSATE: Key =
    Key::new(&["control", "latency", "compensate"], Kind::Bool(false));
pub const UNSTAMPED_DELAY_MS: Key = Key::new(
    &["control", "latency", "unstamped_delay_ms"],
    Kind::Float(5.0),
);
pub const CONTROL_PULSATION_HZ: Key =
    Key::new(&["control", "latency", "pulsation_hz"], Kind::Float(1.0));

pub const COMMAND_DELAY_MS: Key = Key::new(&["plant", "command_delay_ms"], Kind::Float(5.0));
pub const CAMERA_LATENCY_FRAMES: Key =
    Key::new(&["plant", "camera", "latency_frames"], Kind::Integer(2));
pub const CAMERA_EXPOSURE_PERIOD_FRAMES: Key = Key::new(
    &["plant", "camera", "exposure_period_frames"],
    Kind::Integer(2),
);
pub const COIL_GAIN_ERROR_STD: Key = Key::new(
    &["plant", "physics", "coil_gain_error_std"],
    Kind::Float(0.05),
);
pub const DRAG_SHAPE: Key = Key::new(&["plant", "physics", "drag_shape"], Kind::Text("cylinder"));
pub const FLOOR_GAP_M: Key = Key::new(&["plant", "physics", "floor_gap_m"], Kind::Float(3e-6));
pub const PULSATION_HZ: Key = Key::new(&["plant", "physics", "pulsation_hz"], Kind::Float(1.0));
pub const PULSATION_AMPLITUDE: Key = Key::new(
    &["plant", "physics", "pulsation_amplitude"],
    Kind::Float(0.3),
);
pub const FLOW_NOISE_FRACTION: Key = Key::new(
    &["plant", "physics", "flow_noise", "fraction"],
    Kind::Float(0.1),
);
pub const RECIRCULATION_STRENGTH: Key = Key::new(
    &["plant", "physics", "recirculation", "strength_fraction"],
    Kind::Float(0.2),
);

/// Every key above; the check walks this list.
pub const ALL: &[Key] = &[
    SEED,
    DURATION_S,
    FRAME_PERIOD_MS,
    VISCOSITY_CP,
    FLOW_MAP,
    CONTROLLER,
    CONSTRAINED_ALLOCATION,
    USE_ALL_COILS,
    FIELD_HEADING_TURN_DEG,
    FIELD_FOLLOWS_FORCE,
    GAIN_ESTIMATION_ENABLED,
    SMC_K4_N,
    SMC_ETA_S,
    SMC_PHI_M,
    SMC_FLOW_K4_N,
    SMC_FLOW_ETA_S,
    SMC_FLOW_PHI_M,
    VELOCITY_ESTIMATE,
    MAX_CURRENT_SLEW,
    SLEW_YIELD,
    SLEW_YIELD_SHORTFALL,
    SLEW_YIELD_MAX_SLEW,
    LATENCY_COMPENSATE,
    UNSTAMPED_DELAY_MS,
    CONTROL_PULSATION_HZ,
    COMMAND_DELAY_MS,
    CAMERA_LATENCY_FRAMES,
    CAMERA_EXPOSURE_PERIOD_FRAMES,
    COIL_GAIN_ERROR_STD,
    DRAG_SHAPE,
    FLOOR_GAP_M,
    PULSATION_HZ,
    PULSATION_AMPLITUDE,
    FLOW_NOISE_FRACTION,
    RECIRCULATION_STRENGTH,
];

/// Whether a scenario with `key` set to its sample value still parses for every service that
/// reads the key's section: an unknown (renamed, misspelt) field or a value of the wrong type
/// is an error naming it.
pub fn resolves(base: &millinav_kit::scenario::Scenario, key: &Key) -> anyhow::Result<()> {
    let mut doc = crate::scenario_document(base)?;
    let sample: toml::Value = match key.kind {
        Kind::Float(v) => v.into(),
        Kind::Integer(v) => v.into(),
        Kind::Bool(v) => v.into(),
        Kind::Text(v) => v.into(),
        Kind::Table => toml::Table::new().into(),
    };
    key.set(&mut doc, sample)?;
    let text = toml::to_string(&doc)?;
    let scenario =
        millinav_kit::scenario::Scenario::parse(&text, std::path::Path::new("probe.toml"))
            .with_context(|| key.dotted())?;
    let section = key.path[0];
    let parsed = match section {
        // The kit parses these tables itself, denying unknown fields.
        "run" | "fluid" | "trajectory" => Ok(()),
        "plant" => scenario
            .section::<millinav_plant::PlantConfig>("plant")
            .map(drop),
        "control" => scenario
            .section::<millinav_control::ControlConfig>("control")
            .map(drop),
        "flow" => scenario
            .section::<millinav_flow::FlowConfig>("flow")
            .map(drop),
        other => anyhow::bail!("{}: no config type known for [{other}]", key.dotted()),
    };
    parsed.with_context(|| key.dotted())
}

#[cfg(test)]
mod tests {
    use super::*;
    use millinav_kit::scenario::Scenario;

    fn base() -> Scenario {
        Scenario::load(&fieldmaps::data_root().join("scenarios/short.toml")).unwrap()
    }

    #[test]
    fn every_key_resolves_against_the_config_types() {
        let base = base();
        for key in ALL {
            if let Err(e) = resolves(&base, key) {
                panic!("{e:#}");
            }
        }
    }

    #[test]
    fn the_check_refuses_a_misspelt_key_in_each_section() {
        let base = base();
        for path in [
            &["run", "seeds"][..],
            &["fluid", "viscosity"][..],
            &["flow", "maps"][..],
            &["control", "smc", "k4"][..],
            &["control", "latency", "unstamped_delay"][..],
            &["plant", "physics", "floor_gap"][..],
            &["plant", "camera", "latency"][..],
        ] {
            let key = Key::new(path, Kind::Float(1.0));
            let message = format!("{:#}", resolves(&base, &key).unwrap_err());
            assert!(
                message.contains(path.last().unwrap()),
                "{}: {message}",
                key.dotted()
            );
        }
        // A right key with a value of the wrong type is refused too.
        let wrong = Key::new(CONTROLLER.path, Kind::Float(1.0));
        assert!(resolves(&base, &wrong).is_err());
    }

    #[test]
    fn a_key_reads_back_what_it_set_and_remove_keeps_the_table() {
        let mut doc = toml::Table::new();
        CAMERA_LATENCY_FRAMES.set(&mut doc, 3).unwrap();
        assert_eq!(CAMERA_LATENCY_FRAMES.number(&doc), Some(3.0));
        FIELD_HEADING_TURN_DEG
            .set_if_absent(&mut doc, 45.0)
            .unwrap();
        FIELD_HEADING_TURN_DEG
            .set_if_absent(&mut doc, 10.0)
            .unwrap();
        assert_eq!(FIELD_HEADING_TURN_DEG.number(&doc), Some(45.0));
        FLOW_MAP.remove(&mut doc).unwrap();
        assert!(doc["flow"].as_table().unwrap().is_empty());
        assert_eq!(FLOW_MAP.get(&doc), None);
    }
}
