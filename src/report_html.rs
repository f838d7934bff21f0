//! The HTML report of a bake (`bake --html`, `merge --html`): one page a
//! reviewer opens offline to see what a bake did without reading JSON —
//! per light its totals, its shadow-pass savings and its map (the render
//! module's light view, drawn from the bake's own masks), the culled
//! casters as a table that sorts and filters, what was skipped, the
//! settings and the command.
//!
//! The page is self-contained: inline CSS and script, pictures as `data:`
//! URIs, nothing fetched. Every text that comes from the user or the world
//! (names, paths, the settings file) is HTML-escaped. The bytes depend only
//! on the inputs (no timings, no clock).
//!
//! The script answers a self-test for headless browsers: with the URL hash
//! `#selftest=TEXT` it filters the table by TEXT on load and writes the
//! number of rows left visible into `#selftest`; `#selftest=TEXT&click=I,J`
//! first clicks the headers of columns I, J (from 0), in that order, so the
//! rows are sorted as a reader's clicks sort them; any script error is
//! written into `#errors`.

use crate::bake::output::{self, CasterEntry};
use crate::bake::setup::BakeWorld;
use crate::bake::{BakeConfig, BakeResult, LightReport, Severity};
use crate::formats::png_write;
use crate::render::{self, Class, Source};
use crate::scene::Scene;
use std::fmt::Write as _;

/// Longest side of each light's map on the page: enough to see where the
/// culled casters are, small enough that a page of several lights stays a
/// few megabytes.
pub const MAP_MAX_SIDE: u32 = 512;

/// Most culled-caster rows the page lists: beyond this a browser slows to
/// a crawl; the report (`--report`) lists them all.
pub const MAX_ROWS: usize = 100_000;

/// What the page is made from.
pub struct PageInput<'a> {
    pub scene: &'a Scene,
    /// The configuration the bake ran with (its lights index `result.lights`).
    pub config: &'a BakeConfig,
    pub result: &'a BakeResult,
    /// The command as typed.
    pub command: &'a str,
    /// The settings file's name, as given.
    pub settings_file: &'a str,
    /// The settings file's text.
    pub settings_text: &'a str,
}

/// The page, as bytes to write.
pub fn page(input: &PageInput) -> Vec<u8> {
    let mut out = String::new();
    let title = format!("shadowcull bake: {}", input.settings_file);
    let _ = write!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{}</title>\n<script>{ERROR_SCRIPT}</script>\n<style>{STYLE}</style>\n</head>\n<body>\n\
         <h1>{}</h1>\n<p>shadowcull {}</p>\n<pre class=\"command\">{}</pre>\n\
         <div id=\"errors\"></div>\n",
        escape(&title),
        escape(&title),
        env!("CARGO_PKG_VERSION"),
        escape(input.command),
    );
    summary(&mut out, &input.result.lights);
    maps(&mut out, input);
    culled_table(&mut out, input);
    skipped(&mut out, input.result);
    let _ = write!(
        out,
        "<h2>Settings</h2>\n<p>{}</p>\n<pre class=\"settings\">{}</pre>\n\
         <script>{TABLE_SCRIPT}</script>\n</body>\n</html>\n",
        escape(input.settings_file),
        escape(input.settings_text),
    );
    out.into_bytes()
}

/// Per light: its bit, kind, rays, verdicts and the shadow pass before and
/// after culling.
fn summary(out: &mut String, lights: &[LightReport]) {
    out.push_str(
        "<h2>Lights</h2>\n<table class=\"lights\">\n<thead><tr><th>bit</th><th>light</th>\
         <th>kind</th><th>rays</th><th>useful</th><th>culled</th><th>instances</th>\
         <th>draw calls</th><th>triangles</th><th>triangles removed</th></tr></thead>\n<tbody>\n",
    );
    for light in lights {
        let s = &light.savings;
        let pair = |c: &crate::bake::savings::BeforeAfter| format!("{} → {}", c.before, c.after);
        let _ = writeln!(
            out,
            "<tr class=\"light\"><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td>{}</td><td>{:.1}%</td></tr>",
            light.bit,
            escape(&light.name),
            escape(light.kind),
            light.rays,
            light.useful_casters,
            light.culled_casters,
            pair(&s.instances),
            pair(&s.draw_calls),
            pair(&s.triangles),
            100.0 * s.triangles_removed,
        );
    }
    out.push_str("</tbody>\n</table>\n");
}

/// Each light's map from the bake's masks, with the colours' legend.
fn maps(out: &mut String, input: &PageInput) {
    out.push_str("<h2>Maps</h2>\n<p>Each light's shadow map as the light sees it: each texel's front surface, coloured by its verdict, darker farther away.</p>\n<ul class=\"legend\">\n");
    for class in Class::ALL {
        let [r, g, b] = class.colour();
        let _ = writeln!(
            out,
            "<li><span class=\"swatch\" style=\"background:rgb({r},{g},{b})\"></span>{}</li>",
            escape(class.label())
        );
    }
    out.push_str("</ul>\n");
    let world = BakeWorld::new(input.scene);
    for light in &input.result.lights {
        let _ = writeln!(
            out,
            "<figure class=\"map\">\n<figcaption>bit {}: {}</figcaption>",
            light.bit,
            escape(&light.name)
        );
        let source = Source::Baked {
            masks: &input.result.masks,
            bit: light.bit,
        };
        let size = Some((MAP_MAX_SIDE, MAP_MAX_SIDE));
        let picture = render::light_view_in(&world, input.config, light.index, size, source)
            .map_err(|e| e.to_string())
            .and_then(|p| png_write::encode_rgb(p.width, p.height, &p.rgb).map(|png| (p, png)));
        match picture {
            Ok((picture, png)) => {
                let _ = writeln!(
                    out,
                    "<img width=\"{}\" height=\"{}\" alt=\"shadow map of {}\" src=\"data:image/png;base64,{}\">",
                    picture.width,
                    picture.height,
                    escape(&light.name),
                    base64(&png)
                );
            }
            Err(why) => {
                let _ = writeln!(out, "<p class=\"nomap\">no map: {}</p>", escape(&why));
            }
        }
        out.push_str("</figure>\n");
    }
}

/// One row per culled caster and light: the report's casters whose bit
/// for the light is clear (receiver-only groups never cast; speedtrees
/// without a proxy are kept for every light).
fn culled_table(out: &mut String, input: &PageInput) {
    let report = output::report(input.scene, input.result);
    let mut rows = String::new();
    let mut count = 0usize;
    for entry in report.casters.iter() {
        if entry.receiver_only || entry.unmodelled {
            continue;
        }
        for (group, mask) in group_masks(&entry) {
            for light in &input.result.lights {
                if mask & 1u32.wrapping_shl(light.bit) != 0 {
                    continue;
                }
                count += 1;
                if count <= MAX_ROWS {
                    culled_row(&mut rows, &entry, group, &light.name);
                }
            }
        }
    }
    let _ = writeln!(
        out,
        "<h2>Culled casters</h2>\n<p>{count} culled (caster, light) pairs. Click a column's \
         header to sort by it; type to keep the rows where some cell contains the text.</p>"
    );
    if count > MAX_ROWS {
        let _ = writeln!(
            out,
            "<p class=\"warning\">Only the first {MAX_ROWS} are listed; the report (--report) lists every caster.</p>"
        );
    }
    let _ = write!(
        out,
        "<p><label>Filter: <input id=\"filter\" type=\"search\"></label> \
         <output id=\"shown\"></output></p>\n<table id=\"culled\">\n<thead><tr>\
         <th>chunk</th><th>kind</th><th>index</th><th>resources</th><th>group</th><th>light</th>\
         </tr></thead>\n<tbody>\n{rows}</tbody>\n</table>\n"
    );
}

/// The entry's draw calls and their masks: a model's groups by position,
/// a terrain block as one (`None`).
fn group_masks(entry: &CasterEntry) -> Vec<(Option<usize>, u32)> {
    match &entry.groups {
        Some(groups) => groups
            .iter()
            .enumerate()
            .map(|(g, &mask)| (Some(g), mask))
            .collect(),
        None if entry.kind == "terrain" => vec![(None, entry.mask)],
        None => Vec::new(),
    }
}

fn culled_row(rows: &mut String, entry: &CasterEntry, group: Option<usize>, light: &str) {
    let resources = match (&entry.resources, &entry.spt) {
        (Some(resources), _) => resources.join(", "),
        (None, Some(spt)) => spt.clone(),
        (None, None) => String::new(),
    };
    let number = |n: Option<usize>| n.map(|n| n.to_string()).unwrap_or_default();
    let _ = writeln!(
        rows,
        "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
        escape(&entry.chunk),
        escape(entry.element.unwrap_or(entry.kind)),
        number(entry.index),
        escape(&resources),
        number(group),
        escape(light),
    );
}

/// What the bake left out, warnings and errors first.
fn skipped(out: &mut String, result: &BakeResult) {
    out.push_str("<h2>Warnings and skipped items</h2>\n");
    if result.skipped.is_empty() {
        out.push_str("<p>Nothing skipped.</p>\n");
        return;
    }
    out.push_str(
        "<table class=\"skipped\">\n<thead><tr><th>severity</th><th>what</th><th>why</th></tr></thead>\n<tbody>\n",
    );
    let mut entries: Vec<_> = result.skipped.iter().collect();
    entries.sort_by_key(|s| std::cmp::Reverse(s.severity));
    for entry in entries {
        let severity = match entry.severity {
            Severity::Info => "info",
            Severity::Warning => "warning",
            Severity::Error => "error",
        };
        let _ = writeln!(
            out,
            "<tr class=\"{severity}\"><td>{severity}</td><td>{}</td><td>{}</td></tr>",
            escape(&entry.what),
            escape(&entry.why)
        );
    }
    out.push_str("</tbody>\n</table>\n");
}

/// `text` safe inside an element or a quoted attribute.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Standard base64 with padding (RFC 4648), for `data:` URIs.
fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Registered before anything else runs, so that an error anywhere on
/// the page is shown (and a headless test can read it).
const ERROR_SCRIPT: &str = r#"
window.onerror = function (message, source, line) {
  var box = document.getElementById("errors");
  var text = message + " (line " + line + ")\n";
  if (box) { box.textContent += text; } else { window.pendingErrors = (window.pendingErrors || "") + text; }
};
"#;

const STYLE: &str = r#"
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
pre { background: #f4f4f4; padding: 0.5em; overflow-x: auto; white-space: pre-wrap; }
table { border-collapse: collapse; margin-bottom: 1em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.5em; text-align: left; }
#culled th { cursor: pointer; background: #eee; user-select: none; }
#culled th.up::after { content: " \25B2"; }
#culled th.down::after { content: " \25BC"; }
#errors:not(:empty) { color: #b00; white-space: pre-wrap; border: 1px solid #b00; padding: 0.5em; }
tr.warning td:first-child { color: #a60; font-weight: bold; }
tr.error td:first-child { color: #b00; font-weight: bold; }
.legend { list-style: none; padding: 0; }
.legend li { display: inline-block; margin-right: 1.2em; }
.swatch { display: inline-block; width: 1em; height: 1em; margin-right: 0.3em; vertical-align: middle; border: 1px solid #888; }
figure.map { display: inline-block; margin: 0 1em 1em 0; vertical-align: top; }
figure.map img { image-rendering: pixelated; border: 1px solid #888; max-width: 100%; height: auto; }
"#;

/// Sorting by a clicked header, filtering by the text box, and the
/// self-test (`#selftest=TEXT[&click=I,J…]`).
const TABLE_SCRIPT: &str = r##"
(function () {
  "use strict";
  if (window.pendingErrors) { document.getElementById("errors").textContent += window.pendingErrors; }
  var table = document.getElementById("culled");
  var body = table.tBodies[0];
  var filter = document.getElementById("filter");
  var shown = document.getElementById("shown");
  var rows = Array.prototype.slice.call(body.rows);
  var texts = rows.map(function (row) {
    return Array.prototype.map.call(row.cells, function (cell) { return cell.textContent.toLowerCase(); });
  });
  rows.forEach(function (row, i) { row.dataset.order = i; });
  function applyFilter() {
    var wanted = filter.value.toLowerCase();
    var visible = 0;
    rows.forEach(function (row, i) {
      var keep = wanted === "" || texts[i].some(function (cell) { return cell.indexOf(wanted) >= 0; });
      row.hidden = !keep;
      if (keep) { visible += 1; }
    });
    shown.textContent = visible + " of " + rows.length + " shown";
    return visible;
  }
  function key(row, column) {
    var text = row.cells[column].textContent;
    var number = Number(text);
    return text !== "" && !isNaN(number) ? [0, number, text] : [1, 0, text];
  }
  function compare(a, b) {
    for (var i = 0; i < a.length; i++) {
      if (a[i] < b[i]) { return -1; }
      if (a[i] > b[i]) { return 1; }
    }
    return 0;
  }
  var headers = table.tHead.rows[0].cells;
  Array.prototype.forEach.call(headers, function (header, column) {
    header.addEventListener("click", function () {
      var descending = header.classList.contains("up");
      Array.prototype.forEach.call(headers, function (h) { h.classList.remove("up", "down"); });
      header.classList.add(descending ? "down" : "up");
      var sorted = rows.slice().sort(function (a, b) {
        var order = compare(key(a, column), key(b, column));
        if (descending) { order = -order; }
        return order || a.dataset.order - b.dataset.order;
      });
      sorted.forEach(function (row) { body.appendChild(row); });
    });
  });
  filter.addEventListener("input", applyFilter);
  applyFilter();
  var hash = window.location.hash;
  if (hash.indexOf("#selftest=") === 0) {
    var test = hash.slice("#selftest=".length);
    var at = test.lastIndexOf("&click=");
    if (at >= 0) {
      test.slice(at + "&click=".length).split(",").forEach(function (column) {
        headers[Number(column)].click();
      });
      test = test.slice(0, at);
    }
    filter.value = decodeURIComponent(test);
    var visible = applyFilter();
    var result = document.createElement("output");
    result.id = "selftest";
    result.textContent = String(visible);
    document.body.appendChild(result);
  }
})();
"##;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escape_covers_markup_and_quotes() {
        assert_eq!(
            escape(r#"<a href="x">&'</a>"#),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;&lt;/a&gt;"
        );
        assert_eq!(escape("plain"), "plain");
    }

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (plain, encoded) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(plain.as_bytes()), encoded);
        }
    }
}
