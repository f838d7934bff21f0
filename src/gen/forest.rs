//! The forest preset's content besides the showcase: `<speedtree>`
//! placements in every chunk (22 in one chunk that holds only terrain and
//! trees, as real maps have), the `<speedtrees>` proxies of the settings
//! file that cover them (a `.model` and two parametric shapes), every
//! other chunk item kind a real map holds, and chunks stored as packed
//! binary XML. Decided per chunk from the seed, like the scattered
//! instances, so the `Expected` counts come from the same values.

use super::models::Kind;
use super::world::{det3, make_transform, ChunkPlan, Placement, Shadow, WorldPlan, M43};
use super::xml::{f6, v3, XmlOut};
use crate::formats::{packed_xml, xml, Section};
use crate::rng::{mix, Rng};

/// The chunk of terrain and trees only (grid x, z), and its tree count.
pub(crate) const TREE_CHUNK: (i32, i32) = (1, 1);
pub(crate) const TREES_IN_TREE_CHUNK: usize = 22;

/// Which `<tree>` rule of the forest's settings covers a `.spt`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum TreeProxy {
    /// `sets/gen/proxies/bush.model`.
    Bush,
    /// A parametric trunk and cone crown.
    Pine,
    /// The catch-all rule: a parametric trunk and ellipsoid crown.
    Broadleaf,
}

/// The `.spt` names the forest places, with the rule that covers each.
pub(crate) const SPTS: [(&str, TreeProxy); 5] = [
    ("speedtree/forest/Bush2_1.spt", TreeProxy::Bush),
    ("speedtree/forest/Bush3.spt", TreeProxy::Bush),
    ("speedtree/forest/Pine_a.spt", TreeProxy::Pine),
    ("speedtree/forest/Oak1.spt", TreeProxy::Broadleaf),
    ("speedtree/other/Fern.spt", TreeProxy::Broadleaf),
];

/// One `<speedtree>` placement.
#[derive(Debug, Clone)]
pub(crate) struct Tree {
    pub spt: &'static str,
    proxy: TreeProxy,
    /// Chunk-local, row-vector convention.
    pub transform: M43,
    pub seed: u32,
    pub visibility_mask: u32,
    /// Written as `<row0>`..`<row3>` rather than twelve numbers (text
    /// chunks only: packed files store one 12-float value).
    pub rows: bool,
}

impl Tree {
    pub(crate) fn proxy(&self) -> TreeProxy {
        self.proxy
    }
}

/// Whether a chunk is written as packed binary XML: the corners, the
/// tree chunk among them; the centre and the edges stay text.
pub(crate) fn packed(ch: &ChunkPlan) -> bool {
    (ch.gx + ch.gz).rem_euclid(2) == 0 && (ch.gx, ch.gz) != (0, 0)
}

/// The chunk's position in grid order (z, then x), as `plan_frame` lays
/// chunks out.
fn chunk_number(plan: &WorldPlan, ch: &ChunkPlan) -> usize {
    let (g0, g1) = plan.params.grid;
    ((ch.gz - g0) * (g1 - g0 + 1) + (ch.gx - g0)) as usize
}

fn chunk_rng(plan: &WorldPlan, ch: &ChunkPlan, stream: u64) -> Rng {
    Rng::new(mix(plan.seed
        ^ stream
        ^ ((ch.gx as u64) << 20)
        ^ ((ch.gz as u64) << 40)))
}

/// A boulder in each packed chunk but the tree chunk, so packed chunks
/// hold models whose `<shadow>` is written beside their trees'.
pub(crate) fn add_models(plan: &WorldPlan, ch: &mut ChunkPlan) {
    if !packed(ch) || (ch.gx, ch.gz) == TREE_CHUNK {
        return;
    }
    let mut rng = chunk_rng(plan, ch, 0xB0_1DE5);
    let size = plan.params.chunk_size;
    let (lx, lz) = (rng.range(10.0, size - 10.0), rng.range(10.0, size - 10.0));
    let (wx, wz) = (lx + ch.gx as f64 * size, lz + ch.gz as f64 * size);
    let y = plan.hills.height(wx, wz) - 0.05;
    let m = make_transform([1.2, 0.9, 1.1], 0.0, rng.range(0.0, 6.0), [lx, y, lz]);
    ch.placements.push(Placement {
        parts: vec![Kind::Boulder],
        transform: m,
        mirrored: det3(&m) < 0.0,
        shadow: Shadow::Default,
    });
}

/// The chunk's speedtrees: 22 on a jittered grid in the tree chunk, two
/// in the corners of the centre chunk (clear of the showcase), three
/// elsewhere. The tree chunk's first tree is scaled unevenly (a basis row
/// of length 1.69, as real maps have) and its eighth mirrored.
pub(crate) fn trees(plan: &WorldPlan, ch: &ChunkPlan) -> Vec<Tree> {
    let mut rng = chunk_rng(plan, ch, 0x5EED_7EE5);
    let size = plan.params.chunk_size;
    let tree_chunk = (ch.gx, ch.gz) == TREE_CHUNK;
    let spots: Vec<(f64, f64)> = if tree_chunk {
        (0..25)
            .filter(|cell| ![6, 12, 18].contains(cell))
            .take(TREES_IN_TREE_CHUNK)
            .map(|cell| {
                let (cx, cz) = ((cell % 5) as f64, (cell / 5) as f64);
                (
                    5.0 + 9.0 * cx + rng.range(-1.5, 1.5),
                    5.0 + 9.0 * cz + rng.range(-1.5, 1.5),
                )
            })
            .collect()
    } else if (ch.gx, ch.gz) == (0, 0) {
        vec![(4.0, 4.0), (size - 4.0, size - 4.0)]
    } else {
        (0..3)
            .map(|_| (rng.range(4.0, size - 4.0), rng.range(4.0, size - 4.0)))
            .collect()
    };
    let text = !packed(ch);
    spots
        .into_iter()
        .enumerate()
        .map(|(i, (lx, lz))| {
            let (spt, proxy) = SPTS[rng.below(SPTS.len())];
            let base = rng.range(0.8, 1.2);
            let mut scale = [0, 1, 2].map(|_| base * rng.range(0.9, 1.1));
            if tree_chunk && i == 0 {
                scale = [1.3, 1.69, 0.8];
            }
            if tree_chunk && i == 7 {
                scale[0] = -scale[0];
            }
            let (wx, wz) = (lx + ch.gx as f64 * size, lz + ch.gz as f64 * size);
            let y = plan.hills.height(wx, wz) - 0.05;
            Tree {
                spt,
                proxy,
                transform: make_transform(
                    scale,
                    0.0,
                    rng.range(0.0, std::f64::consts::TAU),
                    [lx, y, lz],
                ),
                seed: rng.next_u64() as u32 % 100_000,
                visibility_mask: 0xFF,
                rows: text && i % 2 == 1,
            }
        })
        .collect()
}

/// The other items of chunk number `n` (grid order): water, user data,
/// particles, sound, a light, flora, and a kind shadowcull does not know.
fn other_items(x: &mut XmlOut, n: usize) {
    let identity: M43 = [
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [10.0, 1.0, 10.0],
    ];
    if n.is_multiple_of(3) {
        x.open("vlo");
        x.leaf("uid", &format!("{:08X}.0000A1B2.00000000.0000C3D4", n + 1));
        x.leaf("type", "water");
        x.close();
    }
    if n % 3 == 1 {
        x.open("UserDataObject");
        x.leaf("guid", &format!("{:08X}.00000001.00000002.00000003", n + 7));
        x.leaf("type", "PatrolNode");
        x.transform(&identity);
        x.close();
    }
    if n % 4 == 1 {
        x.open("particles");
        x.leaf("resource", "particles/smoke.xml");
        x.transform(&identity);
        x.leaf("reflectionVisible", "false");
        x.close();
    }
    if n == 2 || n == 6 {
        x.open("audio");
        x.leaf("resource", "sounds/birds");
        x.leaf("position", &v3([12.0, 2.0, 30.0]));
        x.leaf("maxDistance", &f6(250.0));
        x.close();
    }
    if n == 4 {
        x.open("omniLight");
        x.leaf("colour", &v3([255.0, 200.0, 150.0]));
        x.leaf("position", &v3([20.0, 4.0, 20.0]));
        x.leaf("innerRadius", &f6(2.0));
        x.leaf("outerRadius", &f6(8.0));
        x.close();
    }
    if n == 5 {
        x.open("flora");
        x.leaf("resource", "flora/grass.xml");
        x.close();
    }
    if n == 7 {
        x.open("ControlPoint");
        x.leaf("name", "cp1");
        x.leaf("position", &v3([25.0, 0.0, 25.0]));
        x.close();
    }
}

/// The lines of the items `write` makes, one tab deep (the children of a
/// chunk's root).
fn items_text(write: impl FnOnce(&mut XmlOut)) -> String {
    let mut x = XmlOut::new("root");
    write(&mut x);
    let text = String::from_utf8(x.finish()).unwrap_or_default();
    text.lines()
        .filter(|line| *line != "<root>" && *line != "</root>")
        .map(|line| format!("{line}\n"))
        .collect()
}

/// Chunk `ch`'s file: its text (`world::chunk_xml`) with its speedtrees
/// put first (before its models, so file order differs from caster id
/// order) and its other items last; packed for the corner chunks.
pub(crate) fn chunk_file(
    text: Vec<u8>,
    plan: &WorldPlan,
    ch: &ChunkPlan,
    trees: &[Tree],
) -> Vec<u8> {
    let text = String::from_utf8(text).unwrap_or_default();
    let speedtrees = items_text(|x| {
        for tree in trees {
            x.open("speedtree");
            x.leaf("visibilityMask", &tree.visibility_mask.to_string());
            x.leaf("spt", tree.spt);
            x.leaf("seed", &tree.seed.to_string());
            if tree.rows {
                x.transform(&tree.transform);
            } else {
                let numbers: Vec<String> =
                    tree.transform.iter().flatten().map(|&v| f6(v)).collect();
                x.leaf("transform", &numbers.join(" "));
            }
            x.leaf("reflectionVisible", "true");
            x.close();
        }
    });
    let others = items_text(|x| other_items(x, chunk_number(plan, ch)));
    let after_header = text
        .find("</waypointGenerationTime>\n")
        .map_or(0, |i| i + "</waypointGenerationTime>\n".len());
    let end = text.rfind("</root>").unwrap_or(text.len());
    let mut out = String::with_capacity(text.len() + speedtrees.len() + others.len());
    out.push_str(&text[..after_header]);
    out.push_str(&speedtrees);
    out.push_str(&text[after_header..end]);
    out.push_str(&others);
    out.push_str(&text[end..]);
    if !packed(ch) {
        return out.into_bytes();
    }
    match xml::parse(out.as_bytes()) {
        Ok(mut root) => {
            as_packer_stores(&mut root);
            packed_xml::write(&root).unwrap_or_else(|_| out.into_bytes())
        }
        Err(_) => out.into_bytes(),
    }
}

/// Numbers written as `res_packer` stores them: each of a value of
/// numbers in the shortest form of its f32, so a 12-number transform
/// packs as one 12-float value and rows as 3-float values.
fn as_packer_stores(section: &mut Section) {
    let words: Vec<&str> = section.value.split_ascii_whitespace().collect();
    let numbers: Option<Vec<f64>> = words.iter().map(|w| w.parse::<f64>().ok()).collect();
    if let Some(numbers) = numbers.filter(|n| !n.is_empty()) {
        let shortest: Vec<String> = numbers.iter().map(|&v| (v as f32).to_string()).collect();
        section.value = shortest.join(" ");
    }
    for child in &mut section.children {
        as_packer_stores(child);
    }
}

/// The settings file with the forest's `<speedtrees>` proxies: bushes by
/// a `.model`, pines by a trunk and cone, every other tree by the
/// catch-all rule's trunk and ellipsoid.
pub(crate) fn with_proxies(settings: Vec<u8>) -> Vec<u8> {
    let proxies = items_text(|x| {
        x.open("speedtrees");
        x.open("tree");
        x.leaf("spt", "speedtree/*/Bush*.spt");
        x.leaf("model", &Kind::Bush.resource());
        x.close();
        x.open("tree");
        x.leaf("spt", "speedtree/forest/Pine*.spt");
        parametric(x, (0.25, 4.0), (2.0, 6.0, 1.5), Some("cone"));
        x.close();
        x.open("tree");
        x.leaf("spt", "speedtree/**");
        parametric(x, (0.3, 5.0), (2.5, 4.0, 2.0), None);
        x.close();
        x.close();
    });
    let text = String::from_utf8(settings).unwrap_or_default();
    let end = text.rfind("</shadowcull>").unwrap_or(text.len());
    format!("{}{proxies}{}", &text[..end], &text[end..]).into_bytes()
}

/// `<trunk>` (radius, height) and `<crown>` (radius, height, base, shape).
fn parametric(x: &mut XmlOut, trunk: (f64, f64), crown: (f64, f64, f64), shape: Option<&str>) {
    x.open("trunk");
    x.leaf("radius", &f6(trunk.0));
    x.leaf("height", &f6(trunk.1));
    x.close();
    x.open("crown");
    x.leaf("radius", &f6(crown.0));
    x.leaf("height", &f6(crown.1));
    x.leaf("base", &f6(crown.2));
    if let Some(shape) = shape {
        x.leaf("shape", shape);
    }
    x.close();
}
