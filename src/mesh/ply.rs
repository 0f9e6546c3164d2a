//! PLY meshes in (the format BOP ships its object models in): ASCII or binary
//! little-endian, a `vertex` element with `x`, `y`, `z` and a `face` element with a
//! `vertex_indices` (or `vertex_index`) list; every other property and element is read past
//! and dropped. Polygons are split into fans 0,k,k+1 in order, as in OBJ. Errors name what
//! is wrong (the caller adds the file).

use crate::error::{Error, Result};

/// A scalar property type and its size in bytes.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Result<Self> {
        Ok(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            other => return Err(invalid(format!("unknown property type '{other}'"))),
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// The value of little-endian `bytes` (of `self.size()`).
    fn read(self, b: &[u8]) -> f64 {
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Self::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Self::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::F64 => f64::from_le_bytes(std::array::from_fn(|i| b[i])),
        }
    }
}

#[derive(Clone, Debug)]
enum Property {
    Scalar(String, Scalar),
    /// A list: the count's type and the items' type.
    List(String, Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

fn invalid(message: String) -> Error {
    Error::InvalidInput(message)
}

/// Reads values one at a time from the body, ASCII words or little-endian bytes.
enum Body<'a> {
    Ascii(std::str::SplitAsciiWhitespace<'a>),
    Binary(&'a [u8]),
}

impl Body<'_> {
    fn next(&mut self, scalar: Scalar) -> Result<f64> {
        match self {
            Body::Ascii(words) => {
                let word = words
                    .next()
                    .ok_or_else(|| invalid("the data end before the header's counts".into()))?;
                word.parse::<f64>()
                    .map_err(|_| invalid(format!("'{word}' is not a number")))
            }
            Body::Binary(bytes) => {
                let n = scalar.size();
                if bytes.len() < n {
                    return Err(invalid("the data end before the header's counts".into()));
                }
                let value = scalar.read(&bytes[..n]);
                *bytes = &bytes[n..];
                Ok(value)
            }
        }
    }
}

/// Parses a PLY file's bytes into a mesh.
pub(super) fn parse(bytes: &[u8]) -> Result<super::Mesh> {
    const END: &[u8] = b"end_header";
    let end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .ok_or_else(|| invalid("no 'end_header': not a PLY file".into()))?;
    let header =
        std::str::from_utf8(&bytes[..end]).map_err(|_| invalid("the header is not text".into()))?;
    // The body starts after end_header's line break.
    let mut body_at = end + END.len();
    while body_at < bytes.len() && bytes[body_at] != b'\n' {
        body_at += 1;
    }
    let body_bytes = bytes.get(body_at + 1..).unwrap_or(&[]);

    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err(invalid("does not start with 'ply'".into()));
    }
    let mut ascii = None;
    let mut elements: Vec<Element> = Vec::new();
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", "ascii", _] => ascii = Some(true),
            ["format", "binary_little_endian", _] => ascii = Some(false),
            ["format", other, ..] => {
                return Err(invalid(format!(
                    "format '{other}' is not read (ascii and binary_little_endian are)"
                )))
            }
            ["element", name, count] => elements.push(Element {
                name: name.to_string(),
                count: count
                    .parse()
                    .map_err(|_| invalid(format!("element {name}: count '{count}'")))?,
                properties: Vec::new(),
            }),
            ["property", "list", count, item, name] => elements
                .last_mut()
                .ok_or_else(|| invalid("a property before any element".into()))?
                .properties
                .push(Property::List(
                    name.to_string(),
                    Scalar::parse(count)?,
                    Scalar::parse(item)?,
                )),
            ["property", kind, name] => elements
                .last_mut()
                .ok_or_else(|| invalid("a property before any element".into()))?
                .properties
                .push(Property::Scalar(name.to_string(), Scalar::parse(kind)?)),
            _ => {} // comment, obj_info, blank
        }
    }
    let ascii = ascii.ok_or_else(|| invalid("no 'format' line".into()))?;
    let text;
    let mut body = if ascii {
        text = std::str::from_utf8(body_bytes)
            .map_err(|_| invalid("ASCII data are not text".into()))?;
        Body::Ascii(text.split_ascii_whitespace())
    } else {
        Body::Binary(body_bytes)
    };

    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    let mut saw = (false, false);
    for element in &elements {
        let coordinate = |name: &str| {
            element
                .properties
                .iter()
                .position(|p| matches!(p, Property::Scalar(n, _) if n == name))
        };
        let is_vertex = element.name == "vertex";
        let is_face = element.name == "face";
        let xyz = if is_vertex {
            saw.0 = true;
            let at = [coordinate("x"), coordinate("y"), coordinate("z")];
            if at.iter().any(Option::is_none) {
                return Err(invalid("the vertex element lacks x, y or z".into()));
            }
            at.map(|a| a.unwrap_or(0))
        } else {
            [0; 3]
        };
        let indices = element.properties.iter().position(|p| {
            matches!(p, Property::List(n, _, _) if n == "vertex_indices" || n == "vertex_index")
        });
        if is_face {
            saw.1 = true;
            if indices.is_none() {
                return Err(invalid(
                    "the face element has no vertex_indices list".into(),
                ));
            }
        }
        for row in 0..element.count {
            let mut p = [0f32; 3];
            for (k, property) in element.properties.iter().enumerate() {
                match property {
                    Property::Scalar(_, scalar) => {
                        let v = body.next(*scalar)?;
                        if is_vertex {
                            if let Some(c) = xyz.iter().position(|&a| a == k) {
                                p[c] = v as f32;
                            }
                        }
                    }
                    Property::List(_, count, item) => {
                        let n = body.next(*count)?;
                        if !((0.0..=1e6).contains(&n) && n.fract() == 0.0) {
                            return Err(invalid(format!(
                                "{} {row}: a list of {n} items",
                                element.name
                            )));
                        }
                        let values = (0..n as usize)
                            .map(|_| body.next(*item))
                            .collect::<Result<Vec<f64>>>()?;
                        if is_face && Some(k) == indices {
                            if values.len() < 3 {
                                return Err(invalid(format!(
                                    "face {row} has {} corners, needs at least 3",
                                    values.len()
                                )));
                            }
                            let corner = |v: f64| -> Result<u32> {
                                if v >= 0.0 && v.fract() == 0.0 && v < u32::MAX as f64 {
                                    Ok(v as u32)
                                } else {
                                    Err(invalid(format!("face {row}: vertex index {v}")))
                                }
                            };
                            for j in 1..values.len() - 1 {
                                triangles.push([
                                    corner(values[0])?,
                                    corner(values[j])?,
                                    corner(values[j + 1])?,
                                ]);
                            }
                        }
                    }
                }
            }
            if is_vertex {
                positions.push(p);
            }
        }
    }
    match saw {
        (false, _) => Err(invalid("no vertex element".into())),
        (_, false) => Err(invalid("no face element (a point cloud is no mesh)".into())),
        _ => super::Mesh::new(positions, triangles),
    }
}
