//! NumPy arrays in and out. Every array argument is read into the engine's layout (a copy,
//! which the engine's own buffers need anyway, made in one pass whatever the strides) and
//! checked; an error names the argument and what is wrong with it.

use numpy::{PyArray, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// A `ValueError` whose message starts with the argument's name.
pub fn bad(name: &str, what: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{name}: {what}"))
}

/// An array argument's values in C order, and its shape.
pub struct Values<T> {
    pub data: Vec<T>,
    pub shape: Vec<usize>,
}

impl<T> Values<T> {
    /// An error naming `name` unless the shape matches `pattern` (None: any length there),
    /// described to the user as `expected`, e.g. "(V, 3)".
    pub fn expect(self, name: &str, pattern: &[Option<usize>], expected: &str) -> PyResult<Self> {
        let fits = self.shape.len() == pattern.len()
            && self
                .shape
                .iter()
                .zip(pattern)
                .all(|(&n, p)| p.is_none_or(|p| p == n));
        if fits {
            Ok(self)
        } else {
            Err(bad(
                name,
                format!("expected shape {expected}, got {:?}", self.shape),
            ))
        }
    }
}

/// The element types read: what `numpy.asarray` makes of masks, images and indices.
trait Number: Copy {
    fn f64(self) -> f64;
    fn integer(self) -> Option<i64>;
}

macro_rules! number {
    (float: $($t:ty),*) => {$(
        impl Number for $t {
            fn f64(self) -> f64 { self as f64 }
            fn integer(self) -> Option<i64> { None }
        }
    )*};
    (int: $($t:ty),*) => {$(
        impl Number for $t {
            fn f64(self) -> f64 { self as f64 }
            fn integer(self) -> Option<i64> { i64::try_from(self).ok() }
        }
    )*};
}
number!(float: f32, f64);
number!(int: i8, i16, i32, i64, u8, u16, u32, u64);

impl Number for bool {
    fn f64(self) -> f64 {
        self as u8 as f64
    }
    fn integer(self) -> Option<i64> {
        Some(self as i64)
    }
}

/// The kinds of element an argument may have.
#[derive(Clone, Copy, PartialEq)]
enum Kind {
    /// floats or integers (geometry).
    Float,
    /// floats, integers or bool (masks and images).
    Any,
    /// integers (indices).
    Integer,
}

/// `obj` as a NumPy array: itself, a tensor's values (detached from its graph, copied to
/// the host), or what `numpy.asarray` makes of a list or tuple.
fn untyped<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Bound<'py, PyUntypedArray>> {
    if let Ok(array) = obj.cast::<PyUntypedArray>() {
        return Ok(array.clone());
    }
    let tensor = obj.hasattr("requires_grad")? && obj.hasattr("detach")?;
    let obj = &if tensor {
        obj.call_method0("detach")
            .and_then(|t| t.call_method0("cpu"))
            .and_then(|t| t.call_method0("numpy"))
            .map_err(|e| bad(name, format!("a tensor NumPy cannot hold ({e})")))?
    } else {
        obj.clone()
    };
    let array = obj
        .py()
        .import("numpy")?
        .call_method1("asarray", (obj,))
        .map_err(|e| bad(name, format!("not an array ({e})")))?;
    array
        .cast_into::<PyUntypedArray>()
        .map_err(|_| bad(name, "not an array"))
}

/// Reads `array` if its elements are `T`: their values converted by `convert`, in C order.
fn read_typed<'py, T, U>(
    array: &Bound<'py, PyUntypedArray>,
    name: &str,
    convert: impl Fn(T) -> U,
) -> PyResult<Option<Values<U>>>
where
    T: Number + numpy::Element,
{
    let Ok(typed) = array.cast::<PyArrayDyn<T>>() else {
        return Ok(None);
    };
    let readonly = typed
        .try_readonly()
        .map_err(|e| bad(name, format!("cannot be read ({e})")))?;
    let view = readonly.as_array();
    let data = match view.as_slice() {
        Some(slice) => slice.iter().map(|&v| convert(v)).collect(),
        None => view.iter().map(|&v| convert(v)).collect(),
    };
    Ok(Some(Values {
        data,
        shape: view.shape().to_vec(),
    }))
}

/// Reads an array argument of one of `kind`'s element types into `U`.
fn read<U>(
    obj: &Bound<'_, PyAny>,
    name: &str,
    kind: Kind,
    convert: impl Fn(f64, Option<i64>) -> U + Copy,
) -> PyResult<Values<U>> {
    let array = untyped(obj, name)?;
    macro_rules! try_types {
        ($($t:ty),*) => {$(
            if let Some(values) = read_typed(&array, name, |v: $t| convert(v.f64(), v.integer()))? {
                return Ok(values);
            }
        )*};
    }
    if kind != Kind::Integer {
        try_types!(f32, f64);
    }
    if kind == Kind::Any {
        try_types!(bool);
    }
    try_types!(u8, i8, u16, i16, u32, i32, u64, i64);
    let dtype = array.dtype();
    Err(bad(
        name,
        format!(
            "dtype {dtype} is not {}",
            match kind {
                Kind::Float => "a number (float or integer)",
                Kind::Any => "a number or bool",
                Kind::Integer => "an integer",
            }
        ),
    ))
}

/// A number argument (floats or integers) as f64, every value finite.
pub fn floats(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Values<f64>> {
    let values = read(obj, name, Kind::Float, |v, _| v)?;
    finite(&values.data, name)?;
    Ok(values)
}

/// A number argument (floats or integers) as f32 (the device's precision), every value
/// finite.
pub fn floats32(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Values<f32>> {
    let values = read(obj, name, Kind::Float, |v, _| v as f32)?;
    finite(&values.data, name)?;
    Ok(values)
}

/// An image argument (a mask, depth, shading: floats, integers or bool) as f32, every value
/// finite, of shape `(H, W)` or, with `views`, `(views, H, W)` (a single view may drop the
/// first axis).
pub fn image(
    obj: &Bound<'_, PyAny>,
    name: &str,
    (width, height): (u32, u32),
    views: Option<usize>,
) -> PyResult<Vec<f32>> {
    let values = read(obj, name, Kind::Any, |v, _| v as f32)?;
    finite(&values.data, name)?;
    let (h, w) = (height as usize, width as usize);
    let fits = match (views, values.shape.as_slice()) {
        (_, &[rows, columns]) => (rows, columns) == (h, w) && views.unwrap_or(1) == 1,
        (Some(n), &[count, rows, columns]) => (count, rows, columns) == (n, h, w),
        _ => false,
    };
    if !fits {
        let expected = match views {
            Some(n) if n > 1 => format!("({n}, {h}, {w})"),
            _ => format!("({h}, {w}) (the size is (width, height) = ({w}, {h}))"),
        };
        return Err(bad(
            name,
            format!("expected shape {expected}, got {:?}", values.shape),
        ));
    }
    Ok(values.data)
}

/// A mask argument as [`image`] reads it, thresholded as the command line does: 1 where
/// a value is above 0 (bool, 0/1 and 0/255 masks alike), else 0.
pub fn mask(
    obj: &Bound<'_, PyAny>,
    name: &str,
    size: (u32, u32),
    views: Option<usize>,
) -> PyResult<Vec<f32>> {
    let mut values = image(obj, name, size, views)?;
    for v in &mut values {
        *v = if *v > 0.0 { 1.0 } else { 0.0 };
    }
    Ok(values)
}

/// An integer argument (a value past `i64::MAX` reads as -1: no index is that large).
pub fn integers(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Values<i64>> {
    read(obj, name, Kind::Integer, |_, i| i.unwrap_or(-1))
}

/// An error naming `name` at its first value that is NaN or infinite.
fn finite<T: Number>(data: &[T], name: &str) -> PyResult<()> {
    match data.iter().position(|v| !v.f64().is_finite()) {
        None => Ok(()),
        Some(k) => Err(bad(
            name,
            format!("value {} at flat index {k} is not finite", data[k].f64()),
        )),
    }
}

/// A new NumPy array of `shape` holding `data` (C order).
pub fn array<'py, T: numpy::Element>(
    py: Python<'py>,
    data: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    PyArray::from_vec(py, data).reshape(shape)
}
