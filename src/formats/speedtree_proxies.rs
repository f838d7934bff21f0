//! `<speedtrees>` of the settings file (docs/contract.md §3): which geometry
//! stands in for each SpeedTree placement. A `.spt` is SpeedTree's
//! proprietary binary and often not shipped beside the chunks, so the bake
//! never reads one; the settings map `.spt` names (exact or globs) to a
//! `.model` the studio exports for the tree, or to a parametric trunk and
//! crown. The first rule that matches a tree wins. Only the values and the
//! matching are here: `bake_settings` reads them from the file, `scene`
//! builds the geometry.

/// Every `<tree>` rule, in file order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SpeedTreeProxies {
    pub rules: Vec<ProxyRule>,
}

impl SpeedTreeProxies {
    /// The proxy of the first rule one of whose patterns matches `spt`
    /// (a `.spt` resource name), if any.
    pub fn proxy_for(&self, spt: &str) -> Option<&Proxy> {
        self.rules
            .iter()
            .find(|rule| rule.patterns.iter().any(|p| p.matches(spt)))
            .map(|rule| &rule.proxy)
    }

    pub fn is_empty(&self) -> bool {
        self.rules.is_empty()
    }
}

/// One `<tree>`: the `.spt` names it covers and their proxy.
#[derive(Debug, Clone, PartialEq)]
pub struct ProxyRule {
    /// Its `<spt>` patterns (one or more): the rule covers a tree any of
    /// them matches.
    pub patterns: Vec<SptPattern>,
    pub proxy: Proxy,
}

/// The geometry standing in for a tree, in tree space (metres; the
/// placement's transform scales, turns and moves it).
#[derive(Debug, Clone, PartialEq)]
pub enum Proxy {
    /// A `.model` resource, read like a placed model's (LOD 0).
    Model(String),
    /// An opaque trunk and an alpha-tested crown.
    Parametric(ParametricTree),
}

/// A closed opaque trunk standing on the tree's origin and a closed
/// alpha-tested crown above it, both around the tree's y axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParametricTree {
    pub trunk_radius: f64,
    pub trunk_height: f64,
    pub crown_radius: f64,
    pub crown_height: f64,
    /// Height of the crown's lowest point above the tree's origin.
    pub crown_base: f64,
    pub crown_shape: CrownShape,
}

impl ParametricTree {
    /// The name that stands for this shape where a model's resource name
    /// would (one model per distinct shape): every parameter, so two trees
    /// share a model exactly when their parameters are equal. It cannot be
    /// a resource path (it holds spaces and `:`).
    pub fn name(&self) -> String {
        format!(
            "parametric proxy: trunk r {} h {}, {} crown r {} h {} base {}",
            self.trunk_radius,
            self.trunk_height,
            self.crown_shape.name(),
            self.crown_radius,
            self.crown_height,
            self.crown_base
        )
    }
}

/// The crown's solid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CrownShape {
    /// An ellipsoid: `radius` across, `height` tall.
    #[default]
    Ellipsoid,
    /// A cone: a disc of `radius` at the base, its apex `height` above.
    Cone,
}

impl CrownShape {
    pub fn from_name(name: &str) -> Option<CrownShape> {
        match name.to_ascii_lowercase().as_str() {
            "ellipsoid" => Some(CrownShape::Ellipsoid),
            "cone" => Some(CrownShape::Cone),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            CrownShape::Ellipsoid => "ellipsoid",
            CrownShape::Cone => "cone",
        }
    }
}

/// A `.spt` name or glob: `/`-separated segments; in a segment `*` matches
/// any run of characters and `?` one character (never `/`); a whole
/// segment `**` matches any number of segments, none included. Letters
/// match in either case (ASCII), and `\` counts as `/`, as in resource
/// names written on Windows.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SptPattern {
    /// As written, trimmed.
    pub text: String,
    segments: Vec<String>,
}

impl SptPattern {
    /// The pattern `text`, or why it is not one.
    pub fn new(text: &str) -> Result<SptPattern, String> {
        let normal = normalise(text);
        if normal.is_empty() {
            return Err(
                "empty <spt>; give a .spt resource name or a glob such as speedtree/**/Bush*.spt"
                    .into(),
            );
        }
        let segments: Vec<String> = normal.split('/').map(str::to_string).collect();
        if segments.iter().any(String::is_empty) {
            return Err(format!("`{text}` has an empty path segment (`//`)"));
        }
        if let Some(bad) = segments.iter().find(|s| s.contains("**") && *s != "**") {
            return Err(format!(
                "`{text}`: `**` must be a whole segment (`a/**/b`), found `{bad}`; use `*` inside a segment"
            ));
        }
        Ok(SptPattern {
            text: text.trim().to_string(),
            segments,
        })
    }

    /// Whether the two match the same names: equal but for case and the
    /// spelling of separators.
    pub fn same_as(&self, other: &SptPattern) -> bool {
        self.segments == other.segments
    }

    /// Whether the resource name `spt` matches.
    pub fn matches(&self, spt: &str) -> bool {
        let normal = normalise(spt);
        let names: Vec<&str> = normal.split('/').collect();
        // reach[j]: the pattern's segments so far can match names[..j].
        let mut reach = vec![false; names.len() + 1];
        reach[0] = true;
        for segment in &self.segments {
            let mut next = vec![false; names.len() + 1];
            if segment == "**" {
                let mut any = false;
                for j in 0..=names.len() {
                    any |= reach[j];
                    next[j] = any;
                }
            } else {
                for j in 0..names.len() {
                    if reach[j] && segment_matches(segment, names[j]) {
                        next[j + 1] = true;
                    }
                }
            }
            reach = next;
        }
        reach[names.len()]
    }
}

/// Trimmed, `\` as `/`, no leading `/`, ASCII lower case.
fn normalise(name: &str) -> String {
    name.trim()
        .replace('\\', "/")
        .trim_start_matches('/')
        .to_ascii_lowercase()
}

/// One segment against `*` and `?` (both already lower case): the greedy
/// wildcard match that backtracks to the last `*` only.
fn segment_matches(pattern: &str, name: &str) -> bool {
    let (p, n): (Vec<char>, Vec<char>) = (pattern.chars().collect(), name.chars().collect());
    let (mut i, mut j) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while j < n.len() {
        if i < p.len() && (p[i] == '?' || p[i] == n[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some((i, j));
            i += 1;
        } else if let Some((si, sj)) = star {
            i = si + 1;
            j = sj + 1;
            star = Some((si, sj + 1));
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(text: &str) -> SptPattern {
        SptPattern::new(text).unwrap()
    }

    #[test]
    fn globs_match_segments_stars_and_question_marks() {
        let bush = pattern("speedtree/*/Bush*.spt");
        assert!(bush.matches("speedtree/map1/Bush2_1.spt"));
        assert!(bush.matches("speedtree/map1/bush.spt"), "case is ignored");
        assert!(bush.matches("\\speedtree\\map1\\Bush.spt"), "backslashes");
        assert!(
            !bush.matches("speedtree/map1/deep/Bush.spt"),
            "* stays in its segment"
        );
        assert!(!bush.matches("speedtree/Bush.spt"));
        assert!(!bush.matches("speedtree/map1/Oak.spt"));
        let all = pattern("speedtree/**");
        assert!(all.matches("speedtree/a/b/c.spt"));
        assert!(all.matches("speedtree/c.spt"));
        assert!(!all.matches("trees/c.spt"));
        let middle = pattern("speedtree/**/Pine?.spt");
        assert!(
            middle.matches("speedtree/Pine1.spt"),
            "** matches no segment"
        );
        assert!(middle.matches("speedtree/a/b/Pine2.spt"));
        assert!(
            !middle.matches("speedtree/a/Pine12.spt"),
            "? is one character"
        );
        let exact = pattern("speedtree/a/Oak.spt");
        assert!(exact.matches("speedtree/a/oak.SPT"));
        assert!(!exact.matches("speedtree/a/Oak.spt.bak"));
        assert!(pattern("**").matches("anything/at/all.spt"));
        assert!(pattern("*a*b*").matches("xxaxxbxx"));
        assert!(!pattern("*a*b*").matches("xxbxxaxx"));
    }

    #[test]
    fn bad_globs_say_why() {
        assert!(SptPattern::new("  ").unwrap_err().contains("empty <spt>"));
        assert!(SptPattern::new("a//b")
            .unwrap_err()
            .contains("empty path segment"));
        assert!(SptPattern::new("speedtree/a**/b")
            .unwrap_err()
            .contains("whole segment"));
    }
}
