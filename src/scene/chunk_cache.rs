//! A chunk file's parsed items kept in the bake cache. Parsing the XML of
//! every chunk is most of a large world's load; a re-bake after an edit
//! reads the unchanged chunks' items back from entries keyed by the chunk
//! file's bytes instead. The value holds exactly what parsing gives
//! (`formats::chunk::ChunkFile`) and the digest of the chunk with its
//! masks zeroed that the load records as its input, so a chunk read back
//! is indistinguishable from one parsed. Neither changes when a bake
//! writes masks, so the output stores the same value under the key of
//! the bytes it writes.

use crate::cache::codec::{DecodeError, Decoder, Encoder};
use crate::cache::{Cache, Key, Kind};
use crate::digest::Digest;
use crate::formats::chunk::{
    ChunkFile, InstanceElement, InstanceKind, SpeedTreeElement, TerrainElement,
};
use crate::formats::shadow_write::{Place, ShadowSites, Site};
use glam::DMat4;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// A chunk file as the load uses it.
#[derive(Debug, Clone, PartialEq)]
pub struct ParsedChunk {
    pub chunk: ChunkFile,
    /// The digest of the file with its `<shadow>` masks zeroed: what the
    /// load records as the input it read.
    pub canonical: Digest,
    /// Where its `<shadow>`s go (text XML only): the output writes them
    /// there without parsing the file again.
    pub sites: Option<ShadowSites>,
}

/// The key of the [`Kind::Chunk`] entry of a chunk file whose bytes'
/// content key is `content`.
pub fn key(cache: &Cache, content: &Key) -> Key {
    cache.hasher(Kind::Chunk).key(content).finish()
}

/// `parsed` as an entry's value: a table of the distinct strings (element
/// paths and resource names repeat), then the items naming them by index.
pub fn encode(parsed: &ParsedChunk) -> Vec<u8> {
    let mut strings = Strings::default();
    let mut body = Encoder::new();
    let chunk = &parsed.chunk;
    body.bytes(&parsed.canonical.0);
    body.var(strings.index(&chunk.root_name));
    match &chunk.transform {
        Some(m) => matrix(body.u8(1), m),
        None => body.u8(0),
    };
    body.var(chunk.instances.len() as u64);
    for instance in &chunk.instances {
        encode_instance(&mut body, &mut strings, instance);
    }
    body.var(chunk.speedtrees.len() as u64);
    for tree in &chunk.speedtrees {
        encode_speedtree(&mut body, &mut strings, tree);
    }
    match &chunk.terrain {
        Some(t) => {
            body.u8(1).var(strings.index(&t.resource));
            body.var(strings.index(&t.path));
        }
        None => {
            body.u8(0);
        }
    }
    body.var(chunk.items.len() as u64);
    for (tag, count) in &chunk.items {
        body.var(strings.index(tag)).var(*count as u64);
    }
    match &parsed.sites {
        Some(sites) => encode_sites(body.u8(1), sites),
        None => {
            body.u8(0);
        }
    }
    let mut out = Encoder::new();
    out.var(strings.list.len() as u64);
    for s in &strings.list {
        out.str(s);
    }
    let mut bytes = out.into_bytes();
    bytes.extend_from_slice(&body.into_bytes());
    bytes
}

/// The value [`encode`] made, or `None` when the bytes are of another
/// shape (the caller rejects the entry and parses the chunk).
pub fn decode(bytes: &[u8]) -> Option<ParsedChunk> {
    decode_checked(bytes).ok()
}

fn decode_checked(bytes: &[u8]) -> Result<ParsedChunk, DecodeError> {
    let mut d = Decoder::new(bytes);
    let count = d.len(1)?;
    let table = (0..count).map(|_| d.str()).collect::<Result<Vec<_>, _>>()?;
    let strings = Table(&table);
    let canonical = Digest(d.bytes()?.try_into().map_err(|_| DecodeError { at: 0 })?);
    let root_name = strings.get(&mut d)?;
    let transform = match d.u8()? {
        0 => None,
        1 => Some(read_matrix(&mut d)?),
        _ => return Err(DecodeError { at: 0 }),
    };
    let count = d.len(1)?;
    let mut shared = Shared::new(Table(&table));
    let instances = (0..count)
        .map(|_| decode_instance(&mut d, &mut shared))
        .collect::<Result<_, _>>()?;
    let count = d.len(1)?;
    let speedtrees = (0..count)
        .map(|_| decode_speedtree(&mut d, &strings))
        .collect::<Result<_, _>>()?;
    let terrain = match d.u8()? {
        0 => None,
        1 => Some(TerrainElement {
            resource: strings.get(&mut d)?,
            path: strings.get(&mut d)?,
        }),
        _ => return Err(DecodeError { at: 0 }),
    };
    let count = d.len(1)?;
    let mut items = BTreeMap::new();
    for _ in 0..count {
        let tag = strings.get(&mut d)?;
        items.insert(tag, d.var()? as usize);
    }
    let sites = match d.u8()? {
        0 => None,
        1 => Some(decode_sites(&mut d)?),
        _ => return Err(DecodeError { at: 0 }),
    };
    if !d.is_done() {
        return Err(DecodeError { at: 0 });
    }
    Ok(ParsedChunk {
        chunk: ChunkFile {
            root_name,
            transform,
            instances,
            speedtrees,
            terrain,
            items,
        },
        canonical,
        sites,
    })
}

/// The places, each offset as the distance from the one before (they
/// ascend within each list, so most take a byte or two), its length and
/// place in one number, its bits in another.
fn encode_sites(e: &mut Encoder, sites: &ShadowSites) {
    e.u8(sites.depth);
    let mut last = 0u32;
    let mut site = |e: &mut Encoder, site: &Site| {
        let place = Place::ALL
            .iter()
            .position(|p| *p == site.place)
            .unwrap_or(0) as u64;
        e.var(u64::from(site.start.wrapping_sub(last)));
        e.var(u64::from(site.end - site.start) << 2 | place);
        // 0: not a mask; else the bits plus one (masks are small numbers).
        e.var(site.held.map_or(0, |held| u64::from(held) + 1));
        last = site.start;
    };
    for list in [&sites.instances, &sites.speedtrees] {
        e.var(list.len() as u64);
        for s in list.iter() {
            site(e, s);
        }
    }
    match &sites.terrain {
        Some(s) => site(e.u8(1), s),
        None => {
            e.u8(0);
        }
    }
    e.var(sites.extras.len() as u64);
    for (target, range) in &sites.extras {
        e.var(u64::from(*target)).u32(range.start).u32(range.end);
    }
}

fn decode_sites(d: &mut Decoder) -> Result<ShadowSites, DecodeError> {
    let bad = DecodeError { at: 0 };
    let depth = d.u8()?;
    let mut last = 0u32;
    let mut site = |d: &mut Decoder| -> Result<Site, DecodeError> {
        let start = last.wrapping_add(u32::try_from(d.var()?).map_err(|_| bad)?);
        let length_and_place = d.var()?;
        let place = Place::ALL[(length_and_place & 3) as usize];
        let end = u32::try_from(length_and_place >> 2)
            .ok()
            .and_then(|length| start.checked_add(length))
            .ok_or(bad)?;
        let held = match d.var()? {
            0 => None,
            bits => Some(u32::try_from(bits - 1).map_err(|_| bad)?),
        };
        last = start;
        Ok(Site {
            place,
            start,
            end,
            held,
        })
    };
    let mut lists = [Vec::new(), Vec::new()];
    for list in &mut lists {
        let count = d.len(3)?;
        for _ in 0..count {
            list.push(site(d)?);
        }
    }
    let terrain = match d.u8()? {
        0 => None,
        1 => Some(site(d)?),
        _ => return Err(bad),
    };
    let count = d.len(9)?;
    let extras = (0..count)
        .map(|_| {
            let target = u32::try_from(d.var()?).map_err(|_| bad)?;
            Ok((target, d.u32()?..d.u32()?))
        })
        .collect::<Result<_, DecodeError>>()?;
    let [instances, speedtrees] = lists;
    Ok(ShadowSites {
        depth,
        instances,
        speedtrees,
        terrain,
        extras,
    })
}

fn encode_instance(e: &mut Encoder, strings: &mut Strings, instance: &InstanceElement) {
    e.u8(match instance.kind {
        InstanceKind::Model => 0,
        InstanceKind::Shell => 1,
        InstanceKind::SpeedTree => 2,
    });
    e.var(instance.index as u64);
    e.var(instance.resources.len() as u64);
    for resource in instance.resources.iter() {
        e.var(strings.index(resource));
    }
    matrix(e, &instance.transform);
    e.u8(u8::from(instance.casts_shadow));
    e.var(strings.index(&instance.path));
}

fn decode_instance(d: &mut Decoder, shared: &mut Shared) -> Result<InstanceElement, DecodeError> {
    let kind = match d.u8()? {
        0 => InstanceKind::Model,
        1 => InstanceKind::Shell,
        2 => InstanceKind::SpeedTree,
        _ => return Err(DecodeError { at: 0 }),
    };
    let index = d.var()? as usize;
    let count = d.len(1)?;
    Ok(InstanceElement {
        kind,
        index,
        resources: shared.list(d, count)?,
        transform: read_matrix(d)?,
        casts_shadow: read_bool(d)?,
        path: shared.str(d)?,
    })
}

fn encode_speedtree(e: &mut Encoder, strings: &mut Strings, tree: &SpeedTreeElement) {
    e.var(tree.index as u64);
    e.var(strings.index(&tree.spt));
    for value in [tree.seed, tree.visibility_mask] {
        match value {
            Some(v) => e.u8(1).u64(v as u64),
            None => e.u8(0),
        };
    }
    matrix(e, &tree.transform);
    e.var(strings.index(&tree.path));
}

fn decode_speedtree(d: &mut Decoder, strings: &Table) -> Result<SpeedTreeElement, DecodeError> {
    let index = d.var()? as usize;
    let spt = strings.get(d)?;
    let mut integer = || -> Result<Option<i64>, DecodeError> {
        match d.u8()? {
            0 => Ok(None),
            1 => Ok(Some(d.u64()? as i64)),
            _ => Err(DecodeError { at: 0 }),
        }
    };
    let (seed, visibility_mask) = (integer()?, integer()?);
    Ok(SpeedTreeElement {
        index,
        spt,
        seed,
        visibility_mask,
        transform: read_matrix(d)?,
        path: strings.get(d)?,
    })
}

/// A transform's 16 numbers, bit for bit; the zeros and ones that fill
/// most placements take one byte each.
fn matrix<'e>(e: &'e mut Encoder, m: &DMat4) -> &'e mut Encoder {
    for v in m.to_cols_array() {
        match v.to_bits() {
            0 => e.u8(0),
            b if b == 1f64.to_bits() => e.u8(1),
            b if b == (-1f64).to_bits() => e.u8(2),
            _ => e.u8(3).f64(v),
        };
    }
    e
}

fn read_matrix(d: &mut Decoder) -> Result<DMat4, DecodeError> {
    let mut values = [0f64; 16];
    for v in &mut values {
        *v = match d.u8()? {
            0 => 0.0,
            1 => 1.0,
            2 => -1.0,
            3 => d.f64()?,
            _ => return Err(DecodeError { at: 0 }),
        };
    }
    Ok(DMat4::from_cols_array(&values))
}

fn read_bool(d: &mut Decoder) -> Result<bool, DecodeError> {
    match d.u8()? {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(DecodeError { at: 0 }),
    }
}

/// The distinct strings of one value, in order of first use.
#[derive(Default)]
struct Strings {
    list: Vec<String>,
    at: HashMap<String, u64>,
}

impl Strings {
    fn index(&mut self, s: &str) -> u64 {
        if let Some(&i) = self.at.get(s) {
            return i;
        }
        let i = self.list.len() as u64;
        self.list.push(s.to_string());
        self.at.insert(s.to_string(), i);
        i
    }
}

/// A decoded string table.
struct Table<'t>(&'t [String]);

impl Table<'_> {
    fn index(&self, d: &mut Decoder) -> Result<usize, DecodeError> {
        usize::try_from(d.var()?)
            .ok()
            .filter(|&i| i < self.0.len())
            .ok_or(DecodeError { at: 0 })
    }

    fn get(&self, d: &mut Decoder) -> Result<String, DecodeError> {
        Ok(self.0[self.index(d)?].clone())
    }
}

/// The values a chunk's elements share, made once per chunk: a chunk
/// places thousands of instances of a few models, and one allocation per
/// instance for each resource list and tag path was a large share of
/// reading a world back.
struct Shared<'t> {
    table: Table<'t>,
    /// Per string of the table, once asked for.
    strs: Vec<Option<Arc<str>>>,
    /// Each resource list met, by its string indices.
    lists: HashMap<Vec<usize>, Arc<[String]>>,
    /// The list being read (kept to read the next without allocating).
    reading: Vec<usize>,
}

impl<'t> Shared<'t> {
    fn new(table: Table<'t>) -> Shared<'t> {
        let strs = vec![None; table.0.len()];
        Shared {
            table,
            strs,
            lists: HashMap::new(),
            reading: Vec::new(),
        }
    }

    fn str(&mut self, d: &mut Decoder) -> Result<Arc<str>, DecodeError> {
        let i = self.table.index(d)?;
        let table = &self.table;
        Ok(self.strs[i]
            .get_or_insert_with(|| Arc::from(table.0[i].as_str()))
            .clone())
    }

    fn list(&mut self, d: &mut Decoder, count: usize) -> Result<Arc<[String]>, DecodeError> {
        self.reading.clear();
        for _ in 0..count {
            self.reading.push(self.table.index(d)?);
        }
        if let Some(list) = self.lists.get(self.reading.as_slice()) {
            return Ok(list.clone());
        }
        let list: Arc<[String]> = self
            .reading
            .iter()
            .map(|&i| self.table.0[i].clone())
            .collect();
        self.lists.insert(self.reading.clone(), list.clone());
        Ok(list)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::{chunk, xml};

    const CHUNK: &str = "<root>\n\t<transform>\n\t\t<row0>\t0.6 0 -0.8\t</row0>\n\t\t<row1>\t0 1 0\t</row1>\n\t\t<row2>\t0.8 0 0.6\t</row2>\n\t\t<row3>\t100 -2.5 7\t</row3>\n\t</transform>\n\t<shell>\n\t\t<resource>\tsets/a/shell.model\t</resource>\n\t\t<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>\n\t\t</editorOnly>\n\t</shell>\n\t<entity>\n\t\t<type>\tInfo\t</type>\n\t</entity>\n\t<model>\n\t\t<resource>\tsets/b.model\t</resource>\n\t\t<resource>\tsets/a/shell.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t-1 0 0\t</row0>\n\t\t\t<row1>\t0 1 0\t</row1>\n\t\t\t<row2>\t0 0 1\t</row2>\n\t\t\t<row3>\t5.125 6 -7\t</row3>\n\t\t</transform>\n\t</model>\n\t<speedtree>\n\t\t<spt>\ttrees/oak.spt\t</spt>\n\t\t<seed>\t-3\t</seed>\n\t\t<transform>\n\t\t\t<row0>\t1 0 0\t</row0>\n\t\t\t<row1>\t0 1 0\t</row1>\n\t\t\t<row2>\t0 0 1\t</row2>\n\t\t\t<row3>\t1e-300 -0 3\t</row3>\n\t\t</transform>\n\t</speedtree>\n\t<speedtree>\n\t\t<spt>\ttrees/oak.spt\t</spt>\n\t\t<visibilityMask>\t4294967295\t</visibilityMask>\n\t</speedtree>\n\t<terrain>\n\t\t<resource>\t00000000o.cdata/terrain2\t</resource>\n\t</terrain>\n</root>\n";

    fn parsed(text: &str) -> ParsedChunk {
        let root = xml::parse(text.as_bytes()).unwrap();
        ParsedChunk {
            chunk: chunk::parse(&root).unwrap(),
            canonical: Digest::of(text.as_bytes()),
            sites: Some(ShadowSites::find(text.as_bytes(), &root).unwrap()),
        }
    }

    #[test]
    fn a_chunk_decodes_to_exactly_what_parsing_gave() {
        let original = parsed(CHUNK);
        assert_eq!(original.chunk.instances.len(), 2);
        assert_eq!(original.chunk.speedtrees.len(), 2);
        let back = decode(&encode(&original)).expect("decodes");
        assert_eq!(back, original);
        // Bit for bit, signs of zero included.
        let tree = &back.chunk.speedtrees[0].transform;
        assert_eq!(tree.w_axis.y.to_bits(), (-0f64).to_bits());
        assert_eq!(tree.w_axis.x, 1e-300);
    }

    #[test]
    fn elements_read_back_share_their_lists_and_paths() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n\t<model>\n\t\t<resource>\tb.model\t</resource>\n\t</model>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n\t<shell>\n\t\t<resource>\ta.model\t</resource>\n\t</shell>\n</root>\n";
        let original = parsed(text);
        let back = decode(&encode(&original)).expect("decodes");
        assert_eq!(back, original);
        let [a, b, again, shell] = &back.chunk.instances[..] else {
            panic!("four elements");
        };
        assert!(Arc::ptr_eq(&a.resources, &again.resources));
        assert!(Arc::ptr_eq(&a.resources, &shell.resources), "the same list");
        assert!(!Arc::ptr_eq(&a.resources, &b.resources));
        assert!(Arc::ptr_eq(&a.path, &b.path));
        assert_eq!((&*a.path, &*shell.path), ("root/model", "root/shell"));
    }

    #[test]
    fn a_chunk_without_optional_items_round_trips() {
        let original = parsed("<root>\n\t<entity/>\n</root>\n");
        assert_eq!(decode(&encode(&original)), Some(original));
        let packed = ParsedChunk {
            sites: None,
            ..parsed(CHUNK)
        };
        assert_eq!(decode(&encode(&packed)), Some(packed));
    }

    #[test]
    fn places_of_every_kind_round_trip() {
        // A shadow to replace (with a second one to remove), one that is
        // not a mask, self-closing and one-line elements.
        let text = "<root>\n\t<model>\n\t\t<shadow>\t6\t</shadow>\n\t\t<shadow>\t1\t</shadow>\n\t</model>\n\t<model/>\n\t<speedtree><shadow>x</shadow></speedtree>\n\t<terrain><resource>a.cdata/terrain2</resource></terrain>\n</root>\n";
        let original = parsed(text);
        let sites = original.sites.as_ref().unwrap();
        assert_eq!(sites.instances.len(), 2);
        assert_eq!(sites.extras.len(), 1);
        assert_eq!(sites.held(), None, "a value that is not a mask");
        assert_eq!(sites.instances[0].held, Some(6));
        assert_eq!(decode(&encode(&original)), Some(original));
    }

    #[test]
    fn a_value_of_another_shape_is_refused_never_a_panic() {
        let bytes = encode(&parsed(CHUNK));
        for cut in 0..bytes.len() {
            assert_eq!(decode(&bytes[..cut]), None, "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert_eq!(decode(&longer), None);
        for at in 0..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[at] ^= 0x5A;
            // Any answer but a panic; the entry's checksum catches flips
            // before decoding in a bake.
            let _ = decode(&flipped);
        }
    }
}
