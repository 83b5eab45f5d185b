//! Evaluation of the vision service's localizers, apart from the service: scores on a dataset
//! split (`eval`) and the graded image shifts of a real camera the robustness suite applies
//! (`perturb`).

pub mod eval;
pub mod perturb;
