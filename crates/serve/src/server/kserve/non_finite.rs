//! JSON tensors as Triton's clients write them: Python's `json` module writes a non-finite float
//! as the bare tokens `NaN`, `Infinity` and `-Infinity`, which JSON does not have (tritonclient
//! writes a `boxes_2d` row of "no box" that way). Before parsing, such tokens outside strings are
//! quoted (`"NaN"`, ...), and a floating-point tensor reads those strings as the values they name.

use std::borrow::Cow;

/// The non-finite tokens, as they appear in the text and as the value they name.
pub const TOKENS: [(&str, f64); 3] = [("NaN", f64::NAN), ("Infinity", f64::INFINITY), ("-Infinity", f64::NEG_INFINITY)];

/// The value a quoted non-finite token names (`"NaN"`, `"Infinity"`, `"-Infinity"`).
pub fn value_of(s: &str) -> Option<f64> {
    TOKENS.iter().find(|(t, _)| *t == s).map(|(_, v)| *v)
}

/// `text` with every bare `NaN`, `Infinity` and `-Infinity` outside strings quoted; borrowed
/// when there is none. Outside strings JSON's only letters are those of `true`, `false` and
/// `null` (lowercase), so an `N` or an `I` there can only begin one of these tokens; anything
/// else is left for the parser to refuse.
pub fn quote_non_finite(text: &[u8]) -> Cow<'_, [u8]> {
    let mut out: Option<Vec<u8>> = None;
    let (mut in_string, mut escaped) = (false, false);
    let mut copied = 0;
    let mut i = 0;
    while i < text.len() {
        let b = text[i];
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
            i += 1;
            continue;
        }
        let token = match b {
            b'"' => {
                in_string = true;
                None
            }
            b'N' if text[i..].starts_with(b"NaN") => Some((i, 3)),
            b'I' if text[i..].starts_with(b"Infinity") => {
                let minus = i > 0 && text[i - 1] == b'-';
                Some(if minus { (i - 1, 9) } else { (i, 8) })
            }
            _ => None,
        };
        match token {
            Some((start, len)) => {
                let o = out.get_or_insert_with(|| Vec::with_capacity(text.len() + 16));
                o.extend_from_slice(&text[copied..start]);
                o.push(b'"');
                o.extend_from_slice(&text[start..start + len]);
                o.push(b'"');
                copied = start + len;
                i = copied;
            }
            None => i += 1,
        }
    }
    match out {
        None => Cow::Borrowed(text),
        Some(mut o) => {
            o.extend_from_slice(&text[copied..]);
            Cow::Owned(o)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quoted(s: &str) -> String {
        String::from_utf8(quote_non_finite(s.as_bytes()).into_owned()).unwrap()
    }

    #[test]
    fn bare_tokens_are_quoted_and_strings_left_alone() {
        assert_eq!(quoted("[NaN, 1.5, Infinity, -Infinity]"), r#"["NaN", 1.5, "Infinity", "-Infinity"]"#);
        assert_eq!(quoted(r#"{"a":NaN,"b":[-Infinity]}"#), r#"{"a":"NaN","b":["-Infinity"]}"#);
        // inside strings (escaped quotes too) nothing changes
        let s = r#"{"id": "NaN \"Infinity\" -Infinity", "x": [true, false, null, -1e3]}"#;
        assert!(matches!(quote_non_finite(s.as_bytes()), Cow::Borrowed(_)));
        assert_eq!(quoted(r#"["a\\", NaN]"#), r#"["a\\", "NaN"]"#);
        // a near miss is left for the parser to refuse
        assert_eq!(quoted("[Nan, Inf]"), "[Nan, Inf]");
    }

    #[test]
    fn the_quoted_text_parses_and_names_the_values() {
        let v: serde_json::Value = serde_json::from_slice(&quote_non_finite(b"[NaN,-Infinity,Infinity]")).unwrap();
        let vals: Vec<f64> = v.as_array().unwrap().iter().map(|x| value_of(x.as_str().unwrap()).unwrap()).collect();
        assert!(vals[0].is_nan() && vals[1] == f64::NEG_INFINITY && vals[2] == f64::INFINITY);
        assert_eq!(value_of("nan"), None);
    }
}
