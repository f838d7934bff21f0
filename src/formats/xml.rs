//! BigWorld text XML into a [`Section`] tree.
//!
//! BigWorld writes XML loosely: values are padded with tabs, elements mix text
//! and children (`<primitiveGroup>\t0\n\t<material>…`), and the root tag is
//! often a file name such as `<fffb0000o.chunk>` or `<axe.visual>`, which a
//! strict parser rejects when it starts with a digit. This reader is lenient
//! about names but strict about structure (mismatched or unclosed tags are
//! errors with a byte offset), and records every element's byte span so the
//! bake can later rewrite one element and keep the rest of the file byte for
//! byte.

use super::Section;
use crate::error::{FormatError, Location};
use quick_xml::events::{BytesRef, Event};
use quick_xml::Reader;

/// Deeper nesting than this is rejected: no real file comes close, and a
/// hostile file must not exhaust the stack when the tree is dropped.
const MAX_DEPTH: usize = 256;

/// Parses a whole text XML document. Text after the root element's end is
/// ignored, as the engine does.
pub fn parse(bytes: &[u8]) -> Result<Section, FormatError> {
    let (mut reader, bom) = reader(bytes);
    let mut tree = Builder::default();
    loop {
        let start = bom + reader.buffer_position() as usize;
        let event = reader.read_event().map_err(|err| {
            let at = bom + reader.error_position() as usize;
            FormatError::at_byte(at, format!("XML syntax error: {err}"))
        })?;
        let end = bom + reader.buffer_position() as usize;
        match event {
            Event::Start(tag) => tree.start(tag_name(tag.name().as_ref()), start)?,
            Event::Empty(tag) => tree.empty(tag_name(tag.name().as_ref()), start, end),
            Event::End(_) => tree.end(start, end)?,
            Event::Text(text) => tree.text(text.as_ref(), start)?,
            Event::CData(data) => tree.append(&lossy(&data)),
            Event::GeneralRef(entity) => tree.append(&entity_text(&entity)),
            Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_) => {}
            Event::Eof => break,
        }
        // The engine reads only the first top-level element.
        if tree.root.is_some() && tree.stack.is_empty() {
            break;
        }
    }
    tree.finish(bytes.len())
}

/// The event reader every text XML read uses, and where in `bytes` its
/// offsets start: a UTF-8 byte order mark is tolerated, and offsets plus
/// that start are file offsets. White space is kept (values are trimmed
/// as sections), end tags must match.
pub(super) fn reader(bytes: &[u8]) -> (Reader<&[u8]>, usize) {
    let bom = if bytes.starts_with(&[0xEF, 0xBB, 0xBF]) {
        3
    } else {
        0
    };
    let mut reader = Reader::from_reader(&bytes[bom..]);
    let config = reader.config_mut();
    config.trim_text(false);
    config.check_end_names = true;
    config.allow_unmatched_ends = false;
    config.check_comments = false;
    (reader, bom)
}

/// The tree as the events build it.
#[derive(Default)]
struct Builder {
    /// Open elements, innermost last.
    stack: Vec<Section>,
    /// Each open element's text run since its last child (entities arrive
    /// as separate events and must join without gaps).
    runs: Vec<String>,
    root: Option<Section>,
}

impl Builder {
    /// A start tag at byte `start`.
    fn start(&mut self, name: String, start: usize) -> Result<(), FormatError> {
        if self.stack.len() >= MAX_DEPTH {
            return Err(FormatError::at_byte(
                start,
                format!("elements nested deeper than {MAX_DEPTH} levels"),
            ));
        }
        flush_run(&mut self.stack, &mut self.runs);
        self.stack.push(open(&self.stack, name, start));
        self.runs.push(String::new());
        Ok(())
    }

    /// An empty element's tag, spanning `start..end`.
    fn empty(&mut self, name: String, start: usize, end: usize) {
        flush_run(&mut self.stack, &mut self.runs);
        let mut element = open(&self.stack, name, start);
        element.span.end = end;
        self.close(element);
    }

    /// An end tag at `start..end`: closes the innermost open element.
    fn end(&mut self, start: usize, end: usize) -> Result<(), FormatError> {
        flush_run(&mut self.stack, &mut self.runs);
        self.runs.pop();
        let Some(mut element) = self.stack.pop() else {
            return Err(FormatError::at_byte(start, "end tag without a start tag"));
        };
        element.span.end = end;
        self.close(element);
        Ok(())
    }

    /// A finished element becomes its parent's last child, or the root.
    fn close(&mut self, element: Section) {
        match self.stack.last_mut() {
            Some(parent) => parent.children.push(element),
            None => self.root = Some(element),
        }
    }

    /// Text at byte `start`: part of the open element's value; outside
    /// every element, only white space may come before the root.
    fn text(&mut self, text: &[u8], start: usize) -> Result<(), FormatError> {
        if let Some(run) = self.runs.last_mut() {
            run.push_str(&lossy(text));
        } else if self.root.is_none() && !text.iter().all(u8::is_ascii_whitespace) {
            return Err(FormatError::at_byte(
                start,
                "text before the root element: this is not an XML file",
            ));
        }
        Ok(())
    }

    /// Text (CDATA, a resolved entity) added to the open element's run;
    /// outside every element it is ignored.
    fn append(&mut self, text: &str) {
        if let Some(run) = self.runs.last_mut() {
            run.push_str(text);
        }
    }

    /// The root, or the error of a file that ends too soon: located where
    /// the input ended (`len`), in the innermost element still open, since
    /// that is where the file was cut.
    fn finish(self, len: usize) -> Result<Section, FormatError> {
        if let Some(innermost) = self.stack.last() {
            return Err(FormatError::new(
                Location::Element {
                    path: innermost.path.clone(),
                    offset: len as u64,
                },
                "the file ends here, before this element is closed (is the file truncated?)",
            ));
        }
        self.root
            .ok_or_else(|| FormatError::whole_file("no XML element found (empty file?)"))
    }
}

/// The text an entity reference stands for: the five predefined entities
/// and character references; any other stays as written.
fn entity_text(entity: &BytesRef) -> String {
    let name = String::from_utf8_lossy(entity).into_owned();
    match name.as_str() {
        "lt" => "<".to_string(),
        "gt" => ">".to_string(),
        "amp" => "&".to_string(),
        "apos" => "'".to_string(),
        "quot" => "\"".to_string(),
        _ => entity
            .resolve_char_ref()
            .ok()
            .flatten()
            .map(String::from)
            .unwrap_or_else(|| format!("&{name};")),
    }
}

fn tag_name(raw: &[u8]) -> String {
    lossy(raw).into_owned()
}

/// `String::from_utf8_lossy`, with std's faster check for the usual case
/// of valid UTF-8 first: every byte of every file loaded passes here.
fn lossy(raw: &[u8]) -> std::borrow::Cow<'_, str> {
    match std::str::from_utf8(raw) {
        Ok(text) => std::borrow::Cow::Borrowed(text),
        Err(_) => String::from_utf8_lossy(raw),
    }
}

fn open(stack: &[Section], name: String, start: usize) -> Section {
    let path = match stack.last() {
        Some(parent) => {
            let mut path = String::with_capacity(parent.path.len() + 1 + name.len());
            path.push_str(&parent.path);
            path.push('/');
            path.push_str(&name);
            path
        }
        None => name.clone(),
    };
    Section {
        name,
        value: String::new(),
        children: Vec::new(),
        path,
        span: start..start,
    }
}

/// Mixed content: the text runs around children join with one space so
/// `\t0\n\t` before a child and nothing after it still reads as `0`.
fn flush_run(stack: &mut [Section], runs: &mut [String]) {
    let (Some(element), Some(run)) = (stack.last_mut(), runs.last_mut()) else {
        return;
    };
    let value = &mut element.value;
    let piece = run.trim();
    if !piece.is_empty() {
        if !value.is_empty() {
            value.push(' ');
        }
        value.push_str(piece);
    }
    run.clear();
}

/// Escapes a value for writing into text XML.
pub fn escape(text: &str) -> std::borrow::Cow<'_, str> {
    quick_xml::escape::escape(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tab_padded_values_and_mixed_content() {
        let text = b"<axe.visual>\n\t<renderSet>\n\t\t<geometry>\n\t\t\t<primitiveGroup>\t0\n\t\t\t\t<material>\n\t\t\t\t\t<identifier>\taxehead\t</identifier>\n\t\t\t\t</material>\n\t\t\t</primitiveGroup>\n\t\t</geometry>\n\t</renderSet>\n</axe.visual>\n";
        let root = parse(text).unwrap();
        assert_eq!(root.name, "axe.visual");
        let group = root
            .required("renderSet")
            .and_then(|r| r.required("geometry"))
            .and_then(|g| g.required("primitiveGroup"))
            .unwrap();
        assert_eq!(group.value, "0");
        assert_eq!(group.path, "axe.visual/renderSet/geometry/primitiveGroup");
        let id = group.child("material").unwrap().child_text("identifier");
        assert_eq!(id, Some("axehead"));
    }

    #[test]
    fn root_tag_may_start_with_a_digit() {
        let root = parse(b"<0000fffdo.chunk>\n\t<model>\t</model>\n</0000fffdo.chunk>").unwrap();
        assert_eq!(root.name, "0000fffdo.chunk");
        assert_eq!(root.children.len(), 1);
    }

    #[test]
    fn spans_cover_whole_elements() {
        let text = "<root>\n\t<a>\t1\t</a>\n\t<b />\n</root>\n";
        let root = parse(text.as_bytes()).unwrap();
        assert_eq!(&text[root.span.clone()], text.trim_end());
        assert_eq!(&text[root.children[0].span.clone()], "<a>\t1\t</a>");
        assert_eq!(&text[root.children[1].span.clone()], "<b />");
    }

    #[test]
    fn entities_are_decoded() {
        let root = parse(b"<r><v>a &amp; b &lt;c&gt;</v></r>").unwrap();
        assert_eq!(root.child_text("v"), Some("a & b <c>"));
    }

    #[test]
    fn mismatched_tags_are_errors_with_offsets() {
        let err = parse(b"<root>\n<a>1</b>\n</root>").unwrap_err();
        assert!(matches!(err.at, Location::Byte(_)), "{err}");
        assert!(err.message.contains("XML"), "{err}");
    }

    #[test]
    fn truncated_file_names_the_innermost_open_element_where_the_input_ends() {
        let text = b"<root>\n\t<model>\n\t\t<resource>\tx\t</resource>\n";
        let err = parse(text).unwrap_err();
        assert_eq!(
            err.at,
            Location::Element {
                path: "root/model".into(),
                offset: text.len() as u64
            },
            "{err}"
        );
        assert!(err.message.contains("truncated"), "{err}");
    }

    #[test]
    fn empty_and_non_xml_input() {
        assert!(parse(b"").is_err());
        assert!(parse(b"   \n").is_err());
        assert!(parse(b"PK\x03\x04garbage").is_err());
    }

    #[test]
    fn deep_nesting_is_refused_not_a_stack_overflow() {
        let mut text = String::new();
        for _ in 0..100_000 {
            text.push_str("<a>");
        }
        let err = parse(text.as_bytes()).unwrap_err();
        assert!(err.message.contains("nested"), "{err}");
    }

    #[test]
    fn every_prefix_of_a_document_is_handled() {
        let text = b"<root>\n\t<model>\n\t\t<resource>\tsets/a.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t1 0 0\t</row0>\n\t\t</transform>\n\t</model>\n</root>\n";
        for len in 0..text.len() {
            let _ = parse(&text[..len]);
        }
        assert!(parse(text).is_ok());
    }
}
