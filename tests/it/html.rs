//! `bake --html` and `merge --html`: the page loads nothing from the
//! network, lists every light and exactly the culled (caster, light) pairs
//! of the bake's report, escapes the user's text; and, in a headless
//! Chromium, its script runs without errors, its filter keeps the rows a
//! count made here from the report says it should, and a click on a
//! header sorts the rows as a sort made here of the report's rows does.

use serde_json::Value;
use shadowcull::files::write_tree;
use shadowcull::gen::{generate, Preset};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A light name with every character HTML must escape.
const ODD_NAME: &str = r#"sun <&> "x""#;
/// ODD_NAME as the settings file writes it.
const ODD_NAME_XML: &str = r#"sun &lt;&amp;&gt; "x""#;

fn shadowcull(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn ok(output: Output, what: &str) -> Output {
    assert!(
        output.status.success(),
        "{what}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// A `village` bake (its sun renamed to ODD_NAME) with a report and a page.
struct Baked {
    _dir: tempfile::TempDir,
    root: PathBuf,
    page_path: PathBuf,
    page: String,
    report: Value,
}

fn bake_village() -> Baked {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("village");
    write_tree(&root, &generate(Preset::Village, 1).files).unwrap();
    let settings = root.join("bake.xml");
    let text = std::fs::read_to_string(&settings).unwrap();
    let renamed = text.replacen(
        "<name>\tsun\t</name>",
        &format!("<name>{ODD_NAME_XML}</name>"),
        1,
    );
    assert_ne!(renamed, text, "the village settings name a light `sun`");
    std::fs::write(&settings, renamed).unwrap();
    let (report, page_path) = (dir.path().join("report.json"), dir.path().join("page.html"));
    let args = [
        "bake",
        s(&settings),
        "--no-cache",
        "--dry-run",
        "--report",
        s(&report),
        "--html",
        s(&page_path),
        "--quiet",
    ];
    ok(shadowcull(&args), "bake --html");
    Baked {
        page: std::fs::read_to_string(&page_path).unwrap(),
        report: serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap(),
        root,
        page_path,
        _dir: dir,
    }
}

/// The report's culled (caster, light) pairs, each as the texts of the
/// page's row: chunk, kind, index, resources, group, light.
fn culled_rows(report: &Value) -> Vec<[String; 6]> {
    let mut rows = Vec::new();
    for caster in report["casters"].as_array().unwrap() {
        if caster["receiver_only"] == true || caster["unmodelled"] == true {
            continue;
        }
        let masks: Vec<(String, u64)> = match caster["groups"].as_array() {
            Some(groups) => groups
                .iter()
                .enumerate()
                .map(|(g, m)| (g.to_string(), m.as_u64().unwrap()))
                .collect(),
            None if caster["kind"] == "terrain" => {
                vec![(String::new(), caster["mask"].as_u64().unwrap())]
            }
            None => Vec::new(),
        };
        let text = |v: &Value| v.as_str().map(str::to_string).unwrap_or_default();
        let kind = match caster["element"].as_str() {
            Some(element) => element.to_string(),
            None => text(&caster["kind"]),
        };
        let index = caster["index"]
            .as_u64()
            .map(|i| i.to_string())
            .unwrap_or_default();
        let resources = match caster["resources"].as_array() {
            Some(list) => list.iter().map(text).collect::<Vec<_>>().join(", "),
            None => text(&caster["spt"]),
        };
        for (group, mask) in &masks {
            for light in report["lights"].as_array().unwrap() {
                if mask & (1 << light["bit"].as_u64().unwrap()) == 0 {
                    rows.push([
                        text(&caster["chunk"]),
                        kind.clone(),
                        index.clone(),
                        resources.clone(),
                        group.clone(),
                        text(&light["name"]),
                    ]);
                }
            }
        }
    }
    rows
}

/// The rows of the page's culled-caster table.
fn page_rows(page: &str) -> usize {
    let start = page.find("<table id=\"culled\">").expect("a culled table");
    let end = start + page[start..].find("</table>").unwrap();
    page[start..end].matches("<tr><td>").count()
}

/// Every `src=` and `href=` value in `page`.
fn links(page: &str) -> Vec<&str> {
    let mut found = Vec::new();
    for attribute in ["src=\"", "href=\"", "src='", "href='"] {
        for (at, _) in page.match_indices(attribute) {
            let value = &page[at + attribute.len()..];
            let quote = attribute.chars().last().unwrap();
            found.push(&value[..value.find(quote).unwrap()]);
        }
    }
    found
}

#[test]
fn html_page_is_offline_complete_and_escaped() {
    let baked = bake_village();
    let (page, report) = (&baked.page, &baked.report);
    let lower = page.to_lowercase();
    assert!(
        !lower.contains("http://") && !lower.contains("https://"),
        "the page names a network address"
    );
    let lights = report["lights"].as_array().unwrap();
    let pictures = links(page);
    assert_eq!(
        pictures.len(),
        lights.len(),
        "one map per light: {pictures:?}"
    );
    for link in pictures {
        assert!(link.starts_with("data:image/png;base64,"), "{link:.60}");
    }
    for light in lights {
        let name = light["name"].as_str().unwrap();
        let escaped = name
            .replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
            .replace('"', "&quot;");
        let row = format!(
            "<tr class=\"light\"><td>{}</td><td>{escaped}</td>",
            light["bit"]
        );
        assert!(page.contains(&row), "no summary row for light {name}");
    }
    assert!(lights.iter().any(|l| l["name"] == ODD_NAME));
    assert!(!page.contains("<&>"), "the light's name is not escaped");
    // The settings file's text, escaped once more.
    assert!(page.contains("&lt;name&gt;sun &amp;lt;&amp;amp;&amp;gt; &quot;x&quot;&lt;/name&gt;"));
    let culled: u64 = lights
        .iter()
        .map(|l| l["culled_casters"].as_u64().unwrap())
        .sum();
    assert!(culled > 0);
    let rows = culled_rows(report);
    assert_eq!(
        rows.len() as u64,
        culled,
        "the report's pairs and its totals"
    );
    assert_eq!(page_rows(page), rows.len());
}

#[test]
fn html_from_merge_lists_the_same_culled_casters() {
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(Preset::Small, 1).files).unwrap();
    let settings = dir.path().join("bake.xml");
    let partial = dir.path().join("only.part");
    let args = [
        "bake",
        s(&settings),
        "--shard",
        "0/1",
        "--partial",
        s(&partial),
        "--quiet",
    ];
    ok(shadowcull(&args), "the shard");
    let (report, page) = (
        dir.path().join("merged.json"),
        dir.path().join("merged.html"),
    );
    let args = [
        "merge",
        s(&settings),
        s(&partial),
        "--dry-run",
        "--report",
        s(&report),
        "--html",
        s(&page),
        "--quiet",
    ];
    ok(shadowcull(&args), "merge --html");
    let report: Value = serde_json::from_slice(&std::fs::read(report).unwrap()).unwrap();
    let page = std::fs::read_to_string(page).unwrap();
    let rows = culled_rows(&report);
    assert!(!rows.is_empty());
    assert_eq!(page_rows(&page), rows.len());
}

/// The text of the element that starts with `opening` in `dom`.
fn element_text<'a>(dom: &'a str, opening: &str) -> Option<&'a str> {
    let start = dom.find(opening)? + opening.len();
    let end = start + dom[start..].find('<')?;
    Some(&dom[start..end])
}

/// The page's DOM after its script ran in the headless browser with the
/// URL hash `#selftest=TEST`, checked free of script errors.
fn browse(browser: &str, baked: &Baked, test: &str) -> String {
    let profile = baked.root.join("browser-profile");
    let url = format!("file://{}#selftest={test}", s(&baked.page_path));
    let output = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--virtual-time-budget=2000",
            &format!("--user-data-dir={}", s(&profile)),
            "--dump-dom",
            &url,
        ])
        .output()
        .expect("run the browser");
    let dom = String::from_utf8_lossy(&ok(output, "the browser").stdout).into_owned();
    assert_eq!(
        element_text(&dom, "<div id=\"errors\">"),
        Some(""),
        "script errors ({test})"
    );
    dom
}

/// The culled table's rows in the order the DOM holds them, each cell's
/// text unescaped.
fn dom_rows(dom: &str) -> Vec<Vec<String>> {
    let start = dom.find("<table id=\"culled\">").expect("a culled table");
    let table = &dom[start..start + dom[start..].find("</table>").unwrap()];
    let body = &table[table.find("<tbody>").expect("a body")..];
    let unescape = |text: &str| {
        text.replace("&lt;", "<")
            .replace("&gt;", ">")
            .replace("&quot;", "\"")
            .replace("&#39;", "'")
            .replace("&amp;", "&")
    };
    body.split("<tr")
        .skip(1)
        .map(|row| {
            row.split("<td>")
                .skip(1)
                .map(|cell| unescape(&cell[..cell.find("</td>").unwrap()]))
                .collect()
        })
        .collect()
}

/// The order a click on column `column`'s header gives (`descending`
/// after a second click), worked out here: cells that are whole numbers
/// before the others, numbers by value, the rest by text; equal cells keep
/// the report's order.
fn sorted_rows(rows: &[[String; 6]], column: usize, descending: bool) -> Vec<Vec<String>> {
    let key = |row: &[String; 6]| {
        let text = &row[column];
        let number = (!text.is_empty() && text.bytes().all(|b| b.is_ascii_digit()))
            .then(|| text.parse::<u64>().unwrap());
        (number.is_none(), number, text.clone())
    };
    let mut sorted: Vec<&[String; 6]> = rows.iter().collect();
    sorted.sort_by(|a, b| {
        let order = key(a).cmp(&key(b));
        if descending {
            order.reverse()
        } else {
            order
        }
    });
    sorted.into_iter().map(|row| row.to_vec()).collect()
}

#[test]
#[cfg_attr(
    not(shadowcull_browser),
    ignore = "needs a headless Chromium: set SHADOWCULL_BROWSER to its binary"
)]
fn html_page_filters_in_a_headless_browser() {
    let browser = std::env::var("SHADOWCULL_BROWSER").expect("SHADOWCULL_BROWSER");
    let baked = bake_village();
    let rows = culled_rows(&baked.report);
    let first_chunk = rows.first().expect("culled casters")[0].clone();
    for wanted in [first_chunk.as_str(), "spot", "crate", "no such caster"] {
        let lowered = wanted.to_lowercase();
        let expected = rows
            .iter()
            .filter(|row| {
                row.iter()
                    .any(|cell| cell.to_lowercase().contains(&lowered))
            })
            .count();
        let dom = browse(&browser, &baked, &wanted.replace(' ', "%20"));
        let shown = element_text(&dom, "<output id=\"selftest\">")
            .unwrap_or_else(|| panic!("no self-test result in the page for `{wanted}`"));
        assert_eq!(
            shown,
            expected.to_string(),
            "rows kept by the filter `{wanted}`"
        );
    }
}

/// Clicking a header sorts the culled table by that column, a second
/// click the other way: the rows the browser shows are the report's rows
/// sorted here, for a text column, whole-number columns (the group column
/// has empty cells for terrain) and the light.
#[test]
#[cfg_attr(
    not(shadowcull_browser),
    ignore = "needs a headless Chromium: set SHADOWCULL_BROWSER to its binary"
)]
fn html_page_sorts_by_a_clicked_header_in_a_headless_browser() {
    let browser = std::env::var("SHADOWCULL_BROWSER").expect("SHADOWCULL_BROWSER");
    let baked = bake_village();
    let rows = culled_rows(&baked.report);
    assert!(rows.len() > 10, "enough rows to sort");
    let unsorted: Vec<Vec<String>> = rows.iter().map(|row| row.to_vec()).collect();
    same_rows(
        &dom_rows(&browse(&browser, &baked, "")),
        &unsorted,
        "no click",
    );
    for (clicks, column, descending) in [
        ("0,0", 0, true),
        ("2", 2, false),
        ("2,2", 2, true),
        ("4,4", 4, true),
        ("3,5", 5, false),
    ] {
        let expected = sorted_rows(&rows, column, descending);
        assert!(expected != unsorted, "clicks {clicks}: the sort moves rows");
        let shown = dom_rows(&browse(&browser, &baked, &format!("&click={clicks}")));
        same_rows(&shown, &expected, &format!("clicks {clicks}"));
    }
}

/// `shown` equals `expected`, or the first row where they differ is named.
fn same_rows(shown: &[Vec<String>], expected: &[Vec<String>], what: &str) {
    assert_eq!(shown.len(), expected.len(), "{what}: rows");
    if let Some(at) = (0..shown.len()).find(|&i| shown[i] != expected[i]) {
        panic!(
            "{what}: row {at} is {:?}, expected {:?}",
            shown[at], expected[at]
        );
    }
}

/// The page's maps come from the bake's masks (`Source::Baked`): each is
/// the picture of a fresh bake of its light alone, pixel for pixel.
#[test]
fn html_maps_from_the_bake_masks_equal_a_bake_of_each_light() {
    use shadowcull::bake::{self, setup::BakeWorld, BakeConfig};
    use shadowcull::render::{self, Source};
    let settings_file = crate::generated::fixture_dir(Preset::Small).join("bake.xml");
    let settings = shadowcull::files::read_bake_settings(&settings_file).unwrap();
    let scene =
        shadowcull::scene::load_scene(&shadowcull::scene::LoadConfig::from_settings(&settings))
            .unwrap();
    let config = BakeConfig::from_settings(&settings);
    let result = bake::bake(&scene, &config, &bake::Silent).unwrap();
    let world = BakeWorld::new(&scene);
    let size = Some((
        shadowcull::report_html::MAP_MAX_SIDE,
        shadowcull::report_html::MAP_MAX_SIDE,
    ));
    assert!(result.lights.len() > 1);
    for light in &result.lights {
        let masks = Source::Baked {
            masks: &result.masks,
            bit: light.bit,
        };
        let from_masks = render::light_view_in(&world, &config, light.index, size, masks).unwrap();
        let fresh = render::light_view(&scene, &config, light.index, size).unwrap();
        assert_eq!(
            (from_masks.width, from_masks.height),
            (fresh.width, fresh.height)
        );
        assert!(from_masks.width.max(from_masks.height) <= shadowcull::report_html::MAP_MAX_SIDE);
        assert!(
            from_masks.classes == fresh.classes,
            "light {}: the classes differ",
            light.name
        );
        assert!(
            from_masks.rgb == fresh.rgb,
            "light {}: the pixels differ",
            light.name
        );
        assert_eq!(from_masks.light.culled, fresh.light.culled);
    }
}
