//! The one error type of the library: every fallible call returns [`Result`].

use std::path::PathBuf;

/// Everything that can go wrong in vkdr, with enough context to act on.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The Vulkan loader or a layer could not be found or started.
    #[error("Vulkan is not usable here: {0}")]
    Loader(String),
    /// A Vulkan call returned an error code.
    #[error("Vulkan call {call} failed: {result}")]
    Vulkan {
        /// The Vulkan function that failed, e.g. `vkCreateBuffer`.
        call: &'static str,
        /// The returned `VkResult` code, by name.
        result: String,
    },
    /// No physical device fits (or `VKDR_DEVICE` named none).
    #[error("no suitable Vulkan device: {0}")]
    NoDevice(String),
    /// The chosen device lacks features the engine needs.
    #[error("device '{device}' lacks required features: {}", missing.join(", "))]
    MissingFeatures {
        /// Name of the device.
        device: String,
        /// The features it lacks, as `vkdr info` names them.
        missing: Vec<String>,
    },
    /// Device memory could not be allocated.
    #[error("GPU memory allocation failed for '{name}': {reason}")]
    Allocation {
        /// Name of the buffer or image the memory was for (`allocator` when the allocator
        /// itself could not be created).
        name: String,
        /// Why it failed, usually the allocator's message.
        reason: String,
    },
    /// A fence or wait did not signal in time (a software driver can hang instead of
    /// reporting device loss).
    #[error("timed out after {seconds} s waiting for {what}")]
    Timeout {
        /// What was waited for.
        what: &'static str,
        /// How long the wait lasted, seconds.
        seconds: f64,
    },
    /// The validation layer reported errors.
    #[error("Vulkan validation reported {} error(s):\n{}", .0.len(), .0.join("\n"))]
    Validation(Vec<String>),
    /// A request exceeds what the device can do (image size, buffer range, ...).
    #[error("device limit exceeded: {0}")]
    Limit(String),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A file could be read but its content is wrong.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong with its content.
        message: String,
    },
    /// An argument handed in by the caller is invalid.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// The caller's progress callback asked the work to stop
    /// ([`crate::register::OnChunk`]): nothing of it is returned.
    #[error("stopped by its progress callback")]
    Stopped,
}

/// `std::result::Result` with [`Error`] as the default error type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A number for a message: plain where that is short, else in scientific notation (1e300,
/// not three hundred digits).
pub fn show(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e7).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// A file whose contents are not what they should be.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            message: message.into(),
        }
    }
}
