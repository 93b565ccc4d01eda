//! XML text escaping, for every writer of XML or SVG (URDF, ROS launch files, the
//! dashboard's figures): element content and double- or single-quoted attribute values.

/// `s` escaped; control characters XML 1.0 cannot hold (all but tab and newline) become
/// U+FFFD rather than an ill-formed document.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c if (c as u32) < 0x20 && c != '\n' && c != '\t' => out.push('\u{FFFD}'),
            c => out.push(c),
        }
    }
    out
}
