//! The ONNX Runtime library must provide the C API version the `ort` crate was built for
//! (`api-24` in the workspace Cargo.toml). `ort` would find out only when it asks the library
//! for that API, so vision checks the library's own version string first and names the file,
//! its version and the one needed.

use std::ffi::CStr;
use std::path::Path;

/// C API version `ort` uses (`ort::MINOR_VERSION`): the library must be ONNX Runtime 1.x with
/// x at least this (each 1.x release serves the C API versions up to x).
pub const REQUIRED_API_VERSION: u32 = ort::MINOR_VERSION;
// The workspace enables ort's `api-24`; a lower version here means its features changed.
const _: () = assert!(REQUIRED_API_VERSION >= 24);

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OrtVersionError {
    #[error("cannot open the ONNX Runtime library: {0}")]
    Open(String),
    #[error("the library does not export OrtGetApiBase (not ONNX Runtime?)")]
    NotOnnxRuntime,
    #[error("the library's version string {0:?} is not of the form 1.x.y")]
    Unparsable(String),
    #[error(
        "ONNX Runtime {found} is too old: the ort crate needs C API version {required} \
         (ONNX Runtime 1.{required} or a newer 1.x); install the pinned onnxruntime wheel \
         (scripts/setup.sh) or point ORT_DYLIB_PATH at a newer library"
    )]
    TooOld { found: String, required: u32 },
    #[error(
        "ONNX Runtime {found} is not a 1.x release; the ort crate speaks the 1.x C API \
         (version {required}: ONNX Runtime 1.{required} or a newer 1.x)"
    )]
    WrongMajor { found: String, required: u32 },
}

/// Whether ONNX Runtime `version` (e.g. "1.32.0", "1.24.0-dev") serves C API `required`.
pub fn check_version(version: &str, required: u32) -> Result<(), OrtVersionError> {
    let mut parts = version.trim().split(['.', '-', '+']);
    let number = |s: Option<&str>| s.and_then(|s| s.parse::<u32>().ok());
    let (Some(major), Some(minor)) = (number(parts.next()), number(parts.next())) else {
        return Err(OrtVersionError::Unparsable(version.to_string()));
    };
    if major != 1 {
        return Err(OrtVersionError::WrongMajor {
            found: version.to_string(),
            required,
        });
    }
    if minor < required {
        return Err(OrtVersionError::TooOld {
            found: version.to_string(),
            required,
        });
    }
    Ok(())
}

/// Opens the library at `path` and checks its version against `REQUIRED_API_VERSION`. The
/// returned handle keeps the library loaded; hold it until `ort` has loaded the same file, so
/// the library is not unloaded and loaded again in between.
pub fn open_checked(path: &Path) -> Result<libloading::Library, OrtVersionError> {
    // SAFETY: loading runs the library's initialisers; ONNX Runtime's only set up its own
    // globals, and `ort` loads this same file right after.
    let library = unsafe { libloading::Library::new(path) }
        .map_err(|e| OrtVersionError::Open(e.to_string()))?;
    let version = {
        // SAFETY: `OrtGetApiBase` has this signature in every ONNX Runtime release (C API).
        let get_base = unsafe {
            library.get::<unsafe extern "C" fn() -> *const ort::sys::OrtApiBase>(b"OrtGetApiBase")
        }
        .map_err(|_| OrtVersionError::NotOnnxRuntime)?;
        // SAFETY: a plain getter with no preconditions; it returns a static table or null.
        let base = unsafe { get_base() };
        if base.is_null() {
            return Err(OrtVersionError::NotOnnxRuntime);
        }
        // SAFETY: `base` is the library's static, non-null API base; `GetVersionString`
        // returns a static NUL-terminated string that the caller must not free.
        let text = unsafe { ((*base).GetVersionString)() };
        if text.is_null() {
            return Err(OrtVersionError::Unparsable(String::new()));
        }
        // SAFETY: non-null, NUL-terminated and static (see above).
        unsafe { CStr::from_ptr(text) }
            .to_string_lossy()
            .into_owned()
    };
    check_version(&version, REQUIRED_API_VERSION)?;
    Ok(library)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn release_at_or_above_the_api_version_is_accepted() {
        assert_eq!(check_version("1.24.0", 24), Ok(()));
        assert_eq!(check_version("1.32.0", 24), Ok(()));
        assert_eq!(check_version("1.24.1-dev+abc", 24), Ok(()));
    }

    #[test]
    fn older_minor_is_rejected_with_both_versions_named() {
        let err = check_version("1.23.2", 24).unwrap_err();
        assert!(matches!(err, OrtVersionError::TooOld { required: 24, .. }));
        let text = err.to_string();
        assert!(text.contains("1.23.2") && text.contains("1.24"), "{text}");
    }

    #[test]
    fn other_major_and_garbage_are_rejected() {
        assert!(matches!(
            check_version("2.30.0", 24),
            Err(OrtVersionError::WrongMajor { .. })
        ));
        assert!(matches!(
            check_version("0.99.0", 24),
            Err(OrtVersionError::WrongMajor { .. })
        ));
        for bad in ["", "1", "x.24.0", "1.y"] {
            assert_eq!(
                check_version(bad, 24),
                Err(OrtVersionError::Unparsable(bad.to_string())),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn missing_file_and_foreign_library_are_named_errors() {
        let missing = open_checked(Path::new("/nonexistent/libonnxruntime.so")).unwrap_err();
        assert!(matches!(missing, OrtVersionError::Open(_)), "{missing}");
        // The C library is loadable everywhere this runs but has no ONNX Runtime entry point.
        let foreign = open_checked(Path::new("libc.so.6")).unwrap_err();
        assert_eq!(foreign, OrtVersionError::NotOnnxRuntime);
    }
}
