//! The packed variant of a generated world (`shadowcull gen --packed`): a
//! shipped game runs `res_packer` over its resources, so its chunks, models,
//! visuals and `space.settings` are packed binary XML, and its chunks hold
//! items the bake does not model whose values have binary types a text
//! round trip would lose. This variant packs every such file as the engine
//! does and gives each chunk those items: a float holding an integral value
//! (`audio/maxDistance` 250.0, `particles/radius` 2.0), an int of every
//! width (0, 1, 2, 4 and 8 bytes), a big unsigned kept as a string, bools,
//! a blob, an encrypted blob and a 12-float matrix; so tests can check that
//! a bake rewrites only its `<shadow>` elements (docs/contract.md §5).
//!
//! Models, placements and terrain are those of the text world, so a packed
//! world bakes like its text twin.

use super::{generate, GeneratedWorld, Preset};
use crate::error::FormatError;
use crate::formats::packed_xml::{self, Document, Value, ValueType};
use crate::formats::xml;

/// Items added to every packed chunk, as the level editor writes them in
/// text before `res_packer` packs them.
const ITEMS: &str = "<items>
\t<audio>
\t\t<resource>\tsounds/ambient/wind\t</resource>
\t\t<maxDistance>\t250.000000\t</maxDistance>
\t\t<minDistance>\t12.500000\t</minDistance>
\t\t<position>\t10.000000 2.000000 -4.000000\t</position>
\t\t<loop>\ttrue\t</loop>
\t</audio>
\t<particles>
\t\t<resource>\tparticles/smoke.xml\t</resource>
\t\t<radius>\t2.000000\t</radius>
\t\t<pointsPerSecond>\t30.000000\t</pointsPerSecond>
\t\t<transform>
\t\t\t<row0>\t1.000000 0.000000 0.000000\t</row0>
\t\t\t<row1>\t0.000000 1.000000 0.000000\t</row1>
\t\t\t<row2>\t0.000000 0.000000 1.000000\t</row2>
\t\t\t<row3>\t20.000000 0.500000 20.000000\t</row3>
\t\t</transform>
\t\t<reflectionVisible>\tfalse\t</reflectionVisible>
\t</particles>
\t<UserDataObject>
\t\t<guid>\tB5D1D3F2.4C4E0C9A.9BCD8E41.0A1B2C3D\t</guid>
\t\t<type>\tPatrolNode\t</type>
\t\t<properties>
\t\t\t<zero>\t0\t</zero>
\t\t\t<byte>\t-5\t</byte>
\t\t\t<short>\t300\t</short>
\t\t\t<int>\t70000\t</int>
\t\t\t<long>\t5000000000\t</long>
\t\t\t<unsigned>\t18446744073709551615\t</unsigned>
\t\t\t<visible>\ttrue\t</visible>
\t\t\t<thumbnail>\taGkhYmxvYg==\t</thumbnail>
\t\t</properties>
\t</UserDataObject>
\t<vlo>
\t\t<uid>\twater_a1b2c3d4\t</uid>
\t\t<type>\twater\t</type>
\t</vlo>
</items>
";

/// Tag of the encrypted blob added to each user data object's properties
/// (no text spelling packs as one: `res_packer` encrypts whole files).
pub const ENCRYPTED_TAG: &str = "secret";

/// The packed form of one file of a generated world: `.chunk` files with
/// the items above, then packed; `.model`, `.visual` and `space.settings`
/// packed; every other file (binary already, or the settings file the tool
/// reads) as it is.
pub fn pack_file(path: &str, bytes: Vec<u8>) -> Result<Vec<u8>, FormatError> {
    let packs = [".model", ".visual", "space.settings"];
    if path.ends_with(".chunk") {
        pack_chunk(&bytes)
    } else if packs.iter().any(|suffix| path.ends_with(suffix)) {
        packed_xml::write(&xml::parse(&bytes)?)
    } else {
        Ok(bytes)
    }
}

/// A preset's world with every file through [`pack_file`].
pub fn generate_packed(preset: Preset, seed: u64) -> Result<GeneratedWorld, FormatError> {
    let world = generate(preset, seed);
    let files = world
        .files
        .into_iter()
        .map(|(path, bytes)| {
            let bytes = pack_file(&path, bytes)?;
            Ok((path, bytes))
        })
        .collect::<Result<_, FormatError>>()?;
    Ok(GeneratedWorld {
        files,
        expected: world.expected,
    })
}

fn pack_chunk(text: &[u8]) -> Result<Vec<u8>, FormatError> {
    let mut root = xml::parse(text)?;
    let items = xml::parse(ITEMS.as_bytes())?;
    let first_item = root.children.len();
    root.children.extend(items.children);
    let mut document = Document::from_section(&root)?;
    let (index, object) = root
        .children
        .iter()
        .enumerate()
        .skip(first_item)
        .find(|(_, c)| c.name == "UserDataObject")
        .ok_or_else(|| root.error("internal error: no UserDataObject item"))?;
    let properties = object
        .children
        .iter()
        .position(|c| c.name == "properties")
        .ok_or_else(|| object.error("internal error: no properties"))?;
    document.push_value(
        &[index, properties],
        ENCRYPTED_TAG,
        Value {
            kind: ValueType::EncryptedBlob,
            data: packed_xml::encrypt_blob(b"patrol route 7"),
        },
        &root,
    )?;
    document.to_bytes()
}

/// Where each kind of stored value sits in a packed chunk of this variant:
/// `(path below the root, type, bytes)`, for tests that check a rewrite
/// kept them.
pub fn typed_values() -> Vec<(&'static str, ValueType, Vec<u8>)> {
    let int = |v: i64, n: usize| v.to_le_bytes()[..n].to_vec();
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let matrix = floats(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 20.0, 0.5, 20.0]);
    vec![
        ("audio/maxDistance", ValueType::Float, floats(&[250.0])),
        (
            "audio/position",
            ValueType::Float,
            floats(&[10.0, 2.0, -4.0]),
        ),
        ("audio/loop", ValueType::Bool, vec![1]),
        ("particles/radius", ValueType::Float, floats(&[2.0])),
        (
            "particles/pointsPerSecond",
            ValueType::Float,
            floats(&[30.0]),
        ),
        ("particles/transform", ValueType::Float, matrix),
        ("particles/reflectionVisible", ValueType::Bool, Vec::new()),
        ("UserDataObject/properties/zero", ValueType::Int, Vec::new()),
        ("UserDataObject/properties/byte", ValueType::Int, int(-5, 1)),
        (
            "UserDataObject/properties/short",
            ValueType::Int,
            int(300, 2),
        ),
        (
            "UserDataObject/properties/int",
            ValueType::Int,
            int(70000, 4),
        ),
        (
            "UserDataObject/properties/long",
            ValueType::Int,
            int(5_000_000_000, 8),
        ),
        (
            "UserDataObject/properties/unsigned",
            ValueType::String,
            b"18446744073709551615".to_vec(),
        ),
        (
            "UserDataObject/properties/thumbnail",
            ValueType::Blob,
            b"hi!blob".to_vec(),
        ),
        (
            "UserDataObject/properties/secret",
            ValueType::EncryptedBlob,
            packed_xml::encrypt_blob(b"patrol route 7"),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_packed_file_holds_its_types_and_writes_back_byte_for_byte() {
        let text = generate(Preset::Small, 5);
        let packed = generate_packed(Preset::Small, 5).unwrap();
        assert_eq!(
            packed,
            generate_packed(Preset::Small, 5).unwrap(),
            "deterministic"
        );
        assert_eq!(packed.expected, text.expected);
        assert_eq!(packed.files.len(), text.files.len());
        let mut chunks = 0;
        for ((path, bytes), (text_path, text_bytes)) in packed.files.iter().zip(&text.files) {
            assert_eq!(path, text_path);
            if !bytes.starts_with(&packed_xml::MAGIC) {
                assert_eq!(bytes, text_bytes, "{path}: left as it is");
                assert!(
                    !path.ends_with(".chunk") && !path.ends_with(".model"),
                    "{path}"
                );
                continue;
            }
            let document = Document::parse(bytes).unwrap();
            assert_eq!(&document.to_bytes().unwrap(), bytes, "{path}: round trip");
            let back = document.to_section().unwrap();
            let text_root = xml::parse(text_bytes).unwrap();
            assert_eq!(
                back.children
                    .iter()
                    .map(|c| &c.name)
                    .take(text_root.children.len())
                    .collect::<Vec<_>>(),
                text_root
                    .children
                    .iter()
                    .map(|c| &c.name)
                    .collect::<Vec<_>>(),
                "{path}"
            );
            if path.ends_with(".chunk") {
                chunks += 1;
                for (at, kind, data) in typed_values() {
                    let value = document
                        .value_at(at)
                        .unwrap_or_else(|| panic!("{path}: {at}"));
                    assert_eq!((value.kind, &value.data), (kind, &data), "{path}: {at}");
                }
                let model = back.child("model").unwrap();
                let transform = model.child("transform").unwrap();
                assert!(transform.children.is_empty(), "rows packed as a matrix");
                let text_transform = text_root.child("model").unwrap().child("transform");
                assert_eq!(
                    transform.as_matrix().unwrap().as_mat4(),
                    text_transform.unwrap().as_matrix().unwrap().as_mat4(),
                    "the same f32 matrix"
                );
            }
        }
        assert_eq!(chunks, 4, "small is 2×2 chunks");
    }
}
