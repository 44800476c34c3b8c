//! The page and its assets, compiled into the binary: the HTML with the bus as it is now filled
//! in for clients that run no script.

use serde_json::Value;

const PAGE: &str = include_str!("../../assets/dashboard/index.html");
pub(super) const APP_JS: &str = include_str!("../../assets/dashboard/app.js");
pub(super) const OD_JS: &str = include_str!("../../assets/dashboard/od.js");
pub(super) const STYLE: &str = include_str!("../../assets/dashboard/style.css");
pub(super) const UPLOT_JS: &str = include_str!("../../assets/dashboard/uplot/uPlot.iife.min.js");
pub(super) const UPLOT_CSS: &str = include_str!("../../assets/dashboard/uplot/uPlot.min.css");
pub(super) const UPLOT_LICENSE: &str = include_str!("../../assets/dashboard/uplot/LICENSE");

/// [`PAGE`] with the snapshot `snap` filled in.
pub(super) fn render_page(snap: &Value) -> String {
    let rows: String = snap["nodes"]
        .as_array()
        .map(|ns| ns.iter().map(node_row_html).collect())
        .unwrap_or_default();
    let link = format!(
        "snapshot at {:.1} s; updates need JavaScript (reload for new values)",
        snap["t"].as_f64().unwrap_or(0.0)
    );
    PAGE.replacen("<!--ROWS-->", &rows, 1)
        .replacen("<!--LINK-->", &html_escape(&link), 1)
        .replacen(
            "<!--BUS-->",
            &html_escape(&format!("bus {}", snap["bus"].as_str().unwrap_or(""))),
            1,
        )
        .replacen("<!--SNAPSHOT-->", &script_json(snap), 1)
}

/// One row of the node table, as the page's script (`nodeRow` in app.js) writes it.
fn node_row_html(n: &Value) -> String {
    let text = |v: &Value| match v {
        Value::Null => "–".to_string(),
        Value::String(s) => s.clone(),
        v => v.to_string(),
    };
    let model = match (n["product"].as_str(), n["model"].as_str()) {
        (Some(p), Some(m)) => format!("{p} ({m})"),
        _ => "unknown".into(),
    };
    let errreg = match n["error_register"].as_u64() {
        Some(r) => format!("0x{r:02X} ({})", text(&n["error_register_text"])),
        None => "–".into(),
    };
    let cells = [
        ("node", text(&n["node"])),
        ("model", model),
        ("name", text(&n["name"])),
        ("serial", text(&n["serial"])),
        ("nmt", text(&n["nmt"])),
        ("pos", positions_text(n)),
        ("errreg", errreg),
    ];
    let mut out = format!("<tr data-node=\"{}\">", n["node"]);
    for (class, t) in cells {
        out.push_str(&format!("<td class=\"{class}\">{}</td>", html_escape(&t)));
    }
    out.push_str("</tr>");
    out
}

/// The node table's position cell: each channel's position in mm (as `positionsText` in
/// app.js writes it).
fn positions_text(n: &Value) -> String {
    let Some(ps) = n["positions"].as_array().filter(|p| !p.is_empty()) else {
        return "–".into();
    };
    // As many decimals as the node's position step has (3 without one).
    let d = n["resolution"]["position_decimals"].as_u64().unwrap_or(3) as usize;
    let mut out: Vec<String> = ps
        .iter()
        .map(|p| match p.as_f64() {
            Some(mm) => format!("{mm:.d$} mm"),
            None => "no position".into(),
        })
        .collect();
    if n["positions_from"] == "control" {
        out.push("(control state; no TPDO)".into());
    }
    out.join(" · ")
}

fn html_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
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

/// JSON to embed in a `<script>` element: `<`, `>` and `&` only occur inside JSON strings,
/// where their `\u` escapes mean the same, so no `</script>` a device name carries ends it.
fn script_json(v: &Value) -> String {
    v.to_string()
        .replace('<', "\\u003c")
        .replace('>', "\\u003e")
        .replace('&', "\\u0026")
}
