//! The planner library (being written).
