//! File output that never leaves a half-written file: write to a temporary file beside
//! the target, then rename. Also `.npy` and PNG helpers used by the command line, and
//! point sets read from OBJ or `.npy` files.

use std::path::Path;

use glam::DVec3;

use crate::error::{Error, Result};
use crate::Mesh;

/// Points of an OBJ file (its vertices) or of an N x 3 `.npy` (float32 or float64).
pub fn load_points(path: &Path) -> Result<Vec<DVec3>> {
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if !is_npy {
        return Ok(Mesh::load_obj(path)?.points());
    }
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    points_from_npy(&path.display().to_string(), &bytes)
}

/// Points of an N x 3 `.npy` (float32 or float64) held in `bytes`; `name` is used in
/// errors. The header is checked against the data before anything is allocated.
pub fn points_from_npy(name: &str, bytes: &[u8]) -> Result<Vec<DVec3>> {
    use ndarray_npy::ReadNpyExt;
    check_npy_size(name, bytes)?;
    let array = match ndarray::Array2::<f64>::read_npy(bytes) {
        Ok(a) => a,
        Err(_) => ndarray::Array2::<f32>::read_npy(bytes)
            .map_err(|e| {
                Error::InvalidInput(format!(
                    "{name}: expected an N x 3 float32 or float64 array ({e})"
                ))
            })?
            .mapv(|v| v as f64),
    };
    if array.ncols() != 3 {
        return Err(Error::InvalidInput(format!(
            "{name}: expected N x 3 points, got {:?}",
            array.shape()
        )));
    }
    Ok(array
        .rows()
        .into_iter()
        .map(|r| DVec3::new(r[0], r[1], r[2]))
        .collect())
}

/// Writes `value` as strict JSON (indented; a non-finite number is `null`, as
/// `serde_json::json!` makes it) to `path` atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| Error::InvalidInput(format!("{}: {e}", path.display())))?;
    write_atomically(path, (text + "\n").as_bytes())
}

/// Writes `bytes` to `path` atomically (temporary file + rename).
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let file_name = path
        .file_name()
        .ok_or_else(|| Error::InvalidInput(format!("{} is not a file path", path.display())))?;
    let mut temporary = path.to_path_buf();
    temporary.set_file_name(format!(".{}.partial", file_name.to_string_lossy()));
    std::fs::write(&temporary, bytes).map_err(|e| Error::io(&temporary, e))?;
    std::fs::rename(&temporary, path).map_err(|e| Error::io(path, e))
}

/// Writes an array as `.npy`.
pub fn write_npy<A, S, D>(path: &Path, array: &ndarray::ArrayBase<S, D>) -> Result<()>
where
    A: ndarray_npy::WritableElement,
    S: ndarray::Data<Elem = A>,
    D: ndarray::Dimension,
{
    let mut bytes = Vec::new();
    ndarray_npy::WriteNpyExt::write_npy(array, &mut bytes)
        .map_err(|e| Error::format(path, e.to_string()))?;
    write_atomically(path, &bytes)
}

/// Checks that an `.npy` file's header does not claim more data than the file holds, so
/// that a reader never allocates for a lying header (a 200-byte file claiming 1e12 x 3
/// floats aborted the process). `name` is used in the error.
pub fn check_npy_size(name: &str, bytes: &[u8]) -> Result<()> {
    let bad = |why: String| Error::InvalidInput(format!("{name}: {why}"));
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(bad("not an .npy file (no \\x93NUMPY magic)".into()));
    }
    let (length, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        _ => return Err(bad("truncated .npy header".into())),
    };
    let header = bytes
        .get(start..start.saturating_add(length))
        .ok_or_else(|| bad("truncated .npy header".into()))?;
    let header = String::from_utf8_lossy(header);
    let field = |key: &str| {
        let at = header.find(key)? + key.len();
        let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest.to_string())
    };
    let element_bytes: u64 = field("'descr'")
        .and_then(|d| d.get(3..4).and_then(|n| n.parse().ok()))
        .ok_or_else(|| bad("no element type in the .npy header".into()))?;
    let shape = field("'shape'")
        .and_then(|s| Some(s.strip_prefix('(')?.split(')').next()?.to_string()))
        .ok_or_else(|| bad("no shape in the .npy header".into()))?;
    let mut count = 1u64;
    // The product of the sizes other than 0: past isize::MAX bytes it is no array (and
    // ndarray-npy panics on such a shape even when another size is 0).
    let mut nonzero = 1u64;
    for dim in shape.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        let dim: u64 = dim
            .parse()
            .map_err(|_| bad(format!("shape ({shape}) is not a list of sizes")))?;
        count = count.saturating_mul(dim);
        nonzero = nonzero.saturating_mul(dim.max(1));
    }
    if nonzero.saturating_mul(element_bytes.max(1)) > isize::MAX as u64 {
        return Err(bad(format!(
            "the header declares shape ({shape}), larger than any array can be"
        )));
    }
    // At least a byte an element: a reader allocates the shape before it checks the type.
    let declared = count.saturating_mul(element_bytes.max(1));
    let held = (bytes.len() - start - length) as u64;
    if declared > held {
        return Err(bad(format!(
            "the header declares shape ({shape}), {declared} bytes of data, but the file \
             holds {held}"
        )));
    }
    Ok(())
}

/// [`check_npy_size`] for every array of an `.npz` archive whose entries are stored (as
/// numpy's `savez` and vkdr write them): no header may claim more data than the rest of
/// the file holds, so that a reader never allocates for a lying header. Compressed
/// entries show no header here; their readers check the archive's own sizes.
pub fn check_npz_sizes(name: &str, bytes: &[u8]) -> Result<()> {
    const MAGIC: &[u8] = b"\x93NUMPY";
    for at in 0..bytes.len().saturating_sub(MAGIC.len() - 1) {
        if &bytes[at..at + MAGIC.len()] == MAGIC {
            check_npy_size(name, &bytes[at..])?;
        }
    }
    Ok(())
}

/// Writes an RGB(A) or grey image as PNG.
pub fn write_png(path: &Path, image: &image::DynamicImage) -> Result<()> {
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| Error::format(path, e.to_string()))?;
    write_atomically(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::check_npy_size;

    fn npy(array: &ndarray::Array2<f32>) -> Vec<u8> {
        let mut bytes = Vec::new();
        ndarray_npy::WriteNpyExt::write_npy(array, &mut bytes).unwrap();
        bytes
    }

    #[test]
    fn an_honest_npy_passes() {
        let bytes = npy(&ndarray::Array2::zeros((5, 3)));
        check_npy_size("points.npy", &bytes).unwrap();
    }

    #[test]
    fn a_header_claiming_more_than_the_file_holds_is_refused() {
        let honest = npy(&ndarray::Array2::zeros((5, 3)));
        // The header with a different shape (its length changes; the check only needs the
        // declared size against the bytes after it).
        let at = honest.windows(6).position(|w| w == b"(5, 3)").unwrap();
        let lying = [&honest[..at], b"(999999999999, 3)", &honest[at + 6..]].concat();
        let error = check_npy_size("points.npy", &lying)
            .unwrap_err()
            .to_string();
        assert!(error.contains("999999999999"), "{error}");
        assert!(check_npy_size("x.npy", b"not numpy at all").is_err());
        assert!(check_npy_size("x.npy", b"").is_err());
    }
}
