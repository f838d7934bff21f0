//! `space.settings`: the grid bounds and chunk size that place every outdoor
//! chunk in the world (chunk/chunk_space.cpp, terrain settings).

use super::Section;
use crate::error::FormatError;

/// Engine default when a space does not say (`chunkSize` is 14.x only).
pub const DEFAULT_CHUNK_SIZE: f64 = 100.0;

#[derive(Debug, Clone, PartialEq)]
pub struct SpaceSettings {
    /// Inclusive outdoor grid bounds: x in `min_x..=max_x`, z in
    /// `min_z..=max_z` (the file calls z `Y`).
    pub min_x: i32,
    pub max_x: i32,
    pub min_z: i32,
    pub max_z: i32,
    pub chunk_size: f64,
    /// `<singleDir>`: every chunk in the space folder itself, never in
    /// `sep` sub-folders.
    pub single_dir: bool,
    pub terrain_version: Option<i64>,
    pub height_map_size: Option<i64>,
}

impl SpaceSettings {
    pub fn contains(&self, x: i32, z: i32) -> bool {
        (self.min_x..=self.max_x).contains(&x) && (self.min_z..=self.max_z).contains(&z)
    }
}

pub fn parse(root: &Section) -> Result<SpaceSettings, FormatError> {
    let bounds = root.required("bounds")?;
    let bound = |name: &str| -> Result<i32, FormatError> {
        let section = bounds.required(name)?;
        let value = section.as_i64()?;
        // Grid indices are u16 in chunk names; anything wider is not a world.
        if !(-32768..=32767).contains(&value) {
            return Err(section.error(format!("grid bound {value} is outside −32768..32767")));
        }
        Ok(value as i32)
    };
    let (min_x, max_x, min_z, max_z) = (
        bound("minX")?,
        bound("maxX")?,
        bound("minY")?,
        bound("maxY")?,
    );
    if min_x > max_x || min_z > max_z {
        return Err(bounds.error(format!(
            "empty grid: x {min_x}..={max_x}, z {min_z}..={max_z} (min must not exceed max)"
        )));
    }
    let chunk_size = match root.child("chunkSize") {
        Some(section) => {
            let size = section.as_f64()?;
            if !(size.is_finite() && size > 0.0) {
                return Err(
                    section.error(format!("chunkSize must be a positive number, found {size}"))
                );
            }
            size
        }
        None => DEFAULT_CHUNK_SIZE,
    };
    let single_dir = match root.child("singleDir") {
        // The engine treats the element's presence as the flag; an explicit
        // false is honoured too.
        Some(section) if !section.value.is_empty() => section.as_bool()?,
        Some(_) => true,
        None => false,
    };
    let terrain = root.child("terrain");
    let terrain_value = |name: &str| -> Result<Option<i64>, FormatError> {
        terrain
            .and_then(|t| t.child(name))
            .map(Section::as_i64)
            .transpose()
    };
    Ok(SpaceSettings {
        min_x,
        max_x,
        min_z,
        max_z,
        chunk_size,
        single_dir,
        terrain_version: terrain_value("version")?,
        height_map_size: terrain_value("heightMapSize")?,
    })
}

/// `%04x%04xo`: the outdoor chunk at grid (x, z), coordinates as u16.
pub fn outdoor_chunk_name(x: i32, z: i32) -> String {
    format!("{:04x}{:04x}o", x as u16, z as u16)
}

/// The grid (x, z) of an outdoor chunk name (`ffff0000o` → (−1, 0)).
pub fn parse_outdoor_chunk_name(name: &str) -> Option<(i32, i32)> {
    let bytes = name.as_bytes();
    if bytes.len() != 9 || bytes[8] != b'o' || !bytes[..8].iter().all(u8::is_ascii_hexdigit) {
        return None;
    }
    let x = u16::from_str_radix(&name[0..4], 16).ok()? as i16 as i32;
    let z = u16::from_str_radix(&name[4..8], 16).ok()? as i16 as i32;
    Some((x, z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::xml;

    #[test]
    fn chunk_names_round_trip_negative_coordinates() {
        assert_eq!(outdoor_chunk_name(-1, 0), "ffff0000o");
        assert_eq!(parse_outdoor_chunk_name("ffff0000o"), Some((-1, 0)));
        assert_eq!(parse_outdoor_chunk_name("fffb0004o"), Some((-5, 4)));
        for (x, z) in [(0, 0), (-32768, 32767), (17, -300)] {
            assert_eq!(
                parse_outdoor_chunk_name(&outdoor_chunk_name(x, z)),
                Some((x, z))
            );
        }
        assert_eq!(parse_outdoor_chunk_name("00am0002i"), None);
        assert_eq!(parse_outdoor_chunk_name("ffff0000i"), None);
        assert_eq!(parse_outdoor_chunk_name("ffff000o"), None);
    }

    #[test]
    fn defaults_and_bounds() {
        let root = xml::parse(
            b"<space.settings>\n\t<bounds>\n\t\t<minX>\t-5\t</minX>\n\t\t<maxX>\t4\t</maxX>\n\t\t<minY>\t-5\t</minY>\n\t\t<maxY>\t4\t</maxY>\n\t</bounds>\n\t<terrain><version>\t200\t</version><heightMapSize>\t32\t</heightMapSize></terrain>\n</space.settings>",
        )
        .unwrap();
        let settings = parse(&root).unwrap();
        assert_eq!(
            (
                settings.min_x,
                settings.max_x,
                settings.min_z,
                settings.max_z
            ),
            (-5, 4, -5, 4)
        );
        assert_eq!(settings.chunk_size, DEFAULT_CHUNK_SIZE);
        assert!(!settings.single_dir);
        assert_eq!(settings.height_map_size, Some(32));
        assert!(settings.contains(-5, 4) && !settings.contains(5, 0));
    }

    #[test]
    fn bad_values_name_the_element() {
        let missing = xml::parse(b"<s><bounds><minX>0</minX></bounds></s>").unwrap();
        assert!(parse(&missing).unwrap_err().to_string().contains("maxX"));
        let inverted = xml::parse(
            b"<s><bounds><minX>3</minX><maxX>2</maxX><minY>0</minY><maxY>0</maxY></bounds></s>",
        )
        .unwrap();
        assert!(parse(&inverted)
            .unwrap_err()
            .to_string()
            .contains("empty grid"));
        let zero = xml::parse(
            b"<s><bounds><minX>0</minX><maxX>0</maxX><minY>0</minY><maxY>0</maxY></bounds><chunkSize>0</chunkSize></s>",
        )
        .unwrap();
        assert!(parse(&zero).unwrap_err().to_string().contains("chunkSize"));
    }
}
