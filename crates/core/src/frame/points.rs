//! `Points` from JSON without buffering: a flat array of numbers goes straight into a
//! `Vec<f32>` (no intermediate JSON values, so a large point cloud costs 4 bytes a number while
//! parsing), and the `{"b64": …}` object refuses unknown keys. Type errors name the field.

use std::fmt;

use serde::de::{self, Deserialize, Deserializer, MapAccess, SeqAccess, Visitor};

use crate::frame::Points;

struct PointsVisitor;

impl<'de> Visitor<'de> for PointsVisitor {
    type Value = Points;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a flat array of x, y, z numbers or an object {\"b64\": \"…\"}")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Points, A::Error> {
        // The size hint comes from the client: cap what it may reserve up front.
        let mut flat = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
        while let Some(v) = seq.next_element::<f32>()? {
            flat.push(v);
        }
        Ok(Points::Flat(flat))
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Points, A::Error> {
        let mut b64: Option<String> = None;
        while let Some(key) = map.next_key::<String>()? {
            match key.as_str() {
                "b64" => {
                    if b64.is_some() {
                        return Err(de::Error::duplicate_field("b64"));
                    }
                    b64 = Some(map.next_value()?);
                }
                other => return Err(de::Error::unknown_field(other, &["b64"])),
            }
        }
        b64.map(|b64| Points::Encoded { b64 }).ok_or_else(|| de::Error::missing_field("b64"))
    }
}

impl<'de> Deserialize<'de> for Points {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Points, D::Error> {
        d.deserialize_any(PointsVisitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_forms_parse_and_unknown_keys_are_refused() {
        let p: Points = serde_json::from_str("[1, 2, 3.5]").unwrap();
        assert_eq!(p, Points::Flat(vec![1.0, 2.0, 3.5]));
        let p: Points = serde_json::from_str(r#"{"b64": "AAAA"}"#).unwrap();
        assert_eq!(p, Points::Encoded { b64: "AAAA".into() });
        let e = serde_json::from_str::<Points>(r#"{"b64": "AAAA", "extra": 1}"#).unwrap_err();
        assert!(e.to_string().contains("unknown field `extra`"), "{e}");
        assert!(serde_json::from_str::<Points>(r#"[1, "x"]"#).is_err());
        assert!(serde_json::from_str::<Points>(r#""text""#).is_err());
        assert!(serde_json::from_str::<Points>("{}").is_err());
    }
}
