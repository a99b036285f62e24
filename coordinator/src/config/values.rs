//! Validated YAML values, and how a refused value is traced back to its key and line.
//!
//! serde reports a value refused inside a nested mapping at the mapping's start, without the
//! key; [`pinpoint`] finds the key holding the refused value so the message names it.

use serde::{Deserialize, Deserializer, Serialize};

/// Marks a value a validated type refused, so [`pinpoint`] can find its key and line (serde
/// reports such errors at the enclosing mapping).
pub(crate) const REFUSED: &str = "refused value ";

pub(crate) fn refused(value: &str, expectation: &str) -> String {
    format!("{REFUSED}{value}: {expectation}")
}

/// Rewrites `<path>: refused value V: <expectation> at line L ...` into
/// `<path>.<key>: <expectation>, found V at line N`, by finding the key holding `V` in the
/// mapping that starts at line L.
pub(crate) fn pinpoint(text: &str, message: &str) -> String {
    let Some(start) = message.find(REFUSED) else {
        return message.to_string();
    };
    let path = message[..start].trim_end_matches(": ").to_string();
    let rest = &message[start + REFUSED.len()..];
    let Some((value, tail)) = rest.split_once(": ") else {
        return message.to_string();
    };
    let (expectation, position) = match tail.split_once(" at line ") {
        Some((expectation, position)) => (expectation, Some(position)),
        None => (tail, None),
    };
    let first_line: usize = position
        .and_then(|p| p.split_whitespace().next())
        .and_then(|l| l.parse().ok())
        .unwrap_or(1);
    for (index, line) in text.lines().enumerate().skip(first_line.saturating_sub(1)) {
        for segment in line.split(['{', ',', '}']) {
            if let Some((key, found)) = segment.split_once(':')
                && found.trim() == value
            {
                let key = key.trim().trim_start_matches("- ");
                let full = if path.is_empty() {
                    key.to_string()
                } else {
                    format!("{path}.{key}")
                };
                return format!("{full}: {expectation}, found {value} at line {}", index + 1);
            }
        }
    }
    format!("{path}: {expectation}, found {value} (in the mapping at line {first_line})")
}

/// Line (1-based) of the block-style key `path` (e.g. `["stage1", "micro_batch"]`).
pub(crate) fn locate(text: &str, path: &[&str]) -> Option<usize> {
    let mut depth = 0;
    let mut indent: Option<usize> = None;
    for (index, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        let here = line.len() - trimmed.len();
        if indent.is_some_and(|i| here <= i) && !trimmed.is_empty() && depth > 0 {
            return None;
        }
        let deeper = match indent {
            None => here == 0,
            Some(i) => here > i,
        };
        if deeper && trimmed.starts_with(&format!("{}:", path[depth])) {
            depth += 1;
            indent = Some(here);
            if depth == path.len() {
                return Some(index + 1);
            }
        }
    }
    None
}

/// A whole number of at least 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Positive(pub u64);

impl<'de> Deserialize<'de> for Positive {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = u64::deserialize(deserializer)?;
        if value == 0 {
            return Err(serde::de::Error::custom(refused(
                "0",
                "expected a positive whole number",
            )));
        }
        Ok(Self(value))
    }
}

/// A finite number of at least 0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NonNegative(pub f64);

impl<'de> Deserialize<'de> for NonNegative {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = f64::deserialize(deserializer)?;
        if !value.is_finite() || value < 0.0 {
            return Err(serde::de::Error::custom(refused(
                &value.to_string(),
                "expected a finite number >= 0",
            )));
        }
        Ok(Self(value))
    }
}

/// A string with something in it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct NonEmpty(pub String);

impl<'de> Deserialize<'de> for NonEmpty {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = String::deserialize(deserializer)?;
        if value.trim().is_empty() {
            return Err(serde::de::Error::custom(refused(
                "\"\"",
                "expected a non-empty string",
            )));
        }
        Ok(Self(value))
    }
}
