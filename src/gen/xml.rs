//! A text XML writer in the BigWorld tools' own layout (tab indentation,
//! values padded with tabs, `%.6f` floats) so generated files look like, and
//! exercise the same reader paths as, files written by the engine's tools.

use std::fmt::Write as _;

pub(crate) struct XmlOut {
    buf: String,
    stack: Vec<String>,
}

impl XmlOut {
    pub(crate) fn new(root: &str) -> Self {
        let mut out = XmlOut {
            buf: String::with_capacity(4096),
            stack: Vec::new(),
        };
        out.open(root);
        out
    }

    fn indent(&mut self) {
        for _ in 0..self.stack.len() {
            self.buf.push('\t');
        }
    }

    /// `<tag>` on its own line; children follow.
    pub(crate) fn open(&mut self, tag: &str) {
        self.indent();
        let _ = writeln!(self.buf, "<{tag}>");
        self.stack.push(tag.to_string());
    }

    /// Mixed content, as in `<primitiveGroup>\t0` followed by children.
    pub(crate) fn open_value(&mut self, tag: &str, value: &str) {
        self.indent();
        let _ = writeln!(self.buf, "<{tag}>\t{value}");
        self.stack.push(tag.to_string());
    }

    pub(crate) fn close(&mut self) {
        if let Some(tag) = self.stack.pop() {
            self.indent();
            let _ = writeln!(self.buf, "</{tag}>");
        }
    }

    /// `<tag>\tvalue\t</tag>`.
    pub(crate) fn leaf(&mut self, tag: &str, value: &str) {
        self.indent();
        let _ = writeln!(self.buf, "<{tag}>\t{value}\t</{tag}>");
    }

    /// `<tag />`, as the tools write empty sections.
    pub(crate) fn empty(&mut self, tag: &str) {
        self.indent();
        let _ = writeln!(self.buf, "<{tag} />");
    }

    /// A 4-row matrix (rows 0–2 basis, row 3 translation).
    pub(crate) fn transform(&mut self, m: &[[f64; 3]; 4]) {
        self.open("transform");
        for (i, row) in m.iter().enumerate() {
            self.leaf(&format!("row{i}"), &v3(*row));
        }
        self.close();
    }

    pub(crate) fn finish(mut self) -> Vec<u8> {
        while !self.stack.is_empty() {
            self.close();
        }
        self.buf.into_bytes()
    }
}

/// `%.6f`, with negative zero written as zero so that tiny rounding noise
/// cannot make otherwise identical output differ.
pub(crate) fn f6(x: f64) -> String {
    let s = format!("{x:.6}");
    if s == "-0.000000" {
        "0.000000".to_string()
    } else {
        s
    }
}

pub(crate) fn v3(v: [f64; 3]) -> String {
    format!("{} {} {}", f6(v[0]), f6(v[1]), f6(v[2]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_matches_bigworld_text_files() {
        let mut x = XmlOut::new("a.model");
        x.leaf("nodelessVisual", "p/q");
        x.open_value("primitiveGroup", "0");
        x.empty("metaData");
        x.close();
        let s = String::from_utf8(x.finish()).unwrap();
        assert_eq!(
            s,
            "<a.model>\n\t<nodelessVisual>\tp/q\t</nodelessVisual>\n\t<primitiveGroup>\t0\n\t\t<metaData />\n\t</primitiveGroup>\n</a.model>\n"
        );
    }

    #[test]
    fn floats_have_six_decimals_and_no_negative_zero() {
        assert_eq!(f6(-0.0000001), "0.000000");
        assert_eq!(f6(1.5), "1.500000");
        assert_eq!(f6(-2.25), "-2.250000");
        assert_eq!(v3([1.0, -1.0, 0.0]), "1.000000 -1.000000 0.000000");
    }
}
