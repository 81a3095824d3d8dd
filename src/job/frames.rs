//! Frame sequences: a job of many frames names its scene by a pattern with a run of `#`
//! (`frame_####.xml`, as exporters write them) and a range of frames; frame `n`'s scene file is
//! the pattern with the run replaced by `n`, zero-padded to the run's length.

use super::FieldError;
use serde::{Deserialize, Serialize};

/// The most frames one sequence job may have: each is a job of its own in the coordinator.
pub const MAX_FRAMES: u32 = 10_000;

/// The frames of a sequence: `first`, `first + step`, ... up to and including `last` at most.
/// On the wire an object `{"first": 1, "last": 3, "step": 1}` (`step` optional) or a string
/// `"1-3"`, `"1-9:2"` or `"5"`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct FrameRange {
    /// The first frame.
    pub first: u32,
    /// The last frame rendered is the greatest `first + k * step` not above it.
    pub last: u32,
    /// The distance between two frames (at least 1).
    pub step: u32,
}

fn default_step() -> u32 {
    1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FrameRangeObject {
    first: u32,
    last: u32,
    #[serde(default = "default_step")]
    step: u32,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum FrameRangeWire {
    Text(String),
    Object(FrameRangeObject),
}

impl<'de> Deserialize<'de> for FrameRange {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        match FrameRangeWire::deserialize(d)? {
            FrameRangeWire::Text(t) => t.parse().map_err(serde::de::Error::custom),
            FrameRangeWire::Object(o) => Ok(FrameRange {
                first: o.first,
                last: o.last,
                step: o.step,
            }),
        }
    }
}

impl std::str::FromStr for FrameRange {
    type Err = String;

    /// `"N"`, `"FIRST-LAST"` or `"FIRST-LAST:STEP"`.
    fn from_str(s: &str) -> Result<Self, String> {
        let number = |t: &str| {
            t.trim().parse::<u32>().map_err(|_| {
                format!("'{s}' is not a frame range (FIRST-LAST or FIRST-LAST:STEP, e.g. 1-100)")
            })
        };
        let (range, step) = match s.split_once(':') {
            Some((r, st)) => (r, number(st)?),
            None => (s, 1),
        };
        let (first, last) = match range.split_once('-') {
            Some((a, b)) => (number(a)?, number(b)?),
            None => {
                let n = number(range)?;
                (n, n)
            }
        };
        Ok(FrameRange { first, last, step })
    }
}

impl std::fmt::Display for FrameRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}-{}", self.first, self.last)?;
        if self.step != 1 {
            write!(f, ":{}", self.step)?;
        }
        Ok(())
    }
}

impl FrameRange {
    /// Checks the range (`frames` names it in errors): first <= last, step >= 1, at most
    /// `MAX_FRAMES` frames.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.step == 0 {
            return Err(FieldError::new("frames", "step must be at least 1"));
        }
        if self.first > self.last {
            return Err(FieldError::new(
                "frames",
                format!("first ({}) is after last ({})", self.first, self.last),
            ));
        }
        if self.len() > MAX_FRAMES as u64 {
            return Err(FieldError::new(
                "frames",
                format!("{} frames, more than the limit of {MAX_FRAMES}", self.len()),
            ));
        }
        Ok(())
    }

    /// How many frames the range holds (0 when first > last or step is 0).
    pub fn len(&self) -> u64 {
        if self.step == 0 || self.first > self.last {
            return 0;
        }
        (self.last - self.first) as u64 / self.step as u64 + 1
    }

    /// Whether the range holds no frame.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The frames, in order.
    pub fn frames(&self) -> impl Iterator<Item = u32> + '_ {
        (self.first..=self.last).step_by(self.step.max(1) as usize)
    }

    /// Whether `frame` is one of the range's frames.
    pub fn contains(&self, frame: u32) -> bool {
        self.step > 0
            && frame >= self.first
            && frame <= self.last
            && (frame - self.first).is_multiple_of(self.step)
    }
}

/// The byte range of the run of `#` in a file name's last component, if it has exactly one.
fn hash_run(pattern: &str) -> Option<std::ops::Range<usize>> {
    let name_start = pattern.rfind('/').map_or(0, |i| i + 1);
    let name = &pattern[name_start..];
    let start = name.find('#')?;
    let len = name[start..].chars().take_while(|&c| c == '#').count();
    let end = start + len;
    if name[end..].contains('#') {
        return None;
    }
    Some(name_start + start..name_start + end)
}

/// Whether `name` is a frame pattern: its file name has one run of `#`.
pub fn is_pattern(name: &str) -> bool {
    name.contains('#')
}

/// The file of `frame` in `pattern` (the run of `#` replaced by the frame number, zero-padded
/// to the run's length; a longer number is written in full). None when the pattern has no
/// single run of `#` in its file name.
pub fn frame_file(pattern: &str, frame: u32) -> Option<String> {
    let run = hash_run(pattern)?;
    let width = run.len();
    Some(format!(
        "{}{frame:0width$}{}",
        &pattern[..run.start],
        &pattern[run.end..]
    ))
}

/// The frame whose file `name` is in `pattern` (digits, at least as many as the run of `#`,
/// where the run is); None when it is not one of its files.
pub fn frame_of(pattern: &str, name: &str) -> Option<u32> {
    let run = hash_run(pattern)?;
    let (prefix, suffix) = (&pattern[..run.start], &pattern[run.end..]);
    let digits = name.strip_prefix(prefix)?.strip_suffix(suffix)?;
    if digits.len() < run.len() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let frame: u32 = digits.parse().ok()?;
    (frame_file(pattern, frame).as_deref() == Some(name)).then_some(frame)
}

/// Checks a frame pattern (`field` names it in errors): one run of `#`, in the file name.
pub fn validate_pattern(pattern: &str, field: &str) -> Result<(), FieldError> {
    hash_run(pattern).map(|_| ()).ok_or_else(|| {
        FieldError::new(
            field,
            format!(
                "'{pattern}' is not a frame pattern: its file name needs one run of '#' \
                 (frame_####.xml)"
            ),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_parse_from_text_and_objects() {
        let r: FrameRange = serde_json::from_str("\"1-3\"").expect("text");
        assert_eq!(
            r,
            FrameRange {
                first: 1,
                last: 3,
                step: 1
            }
        );
        let r: FrameRange = serde_json::from_str("\"2-9:3\"").expect("text with step");
        assert_eq!(r.frames().collect::<Vec<_>>(), vec![2, 5, 8]);
        assert_eq!(r.len(), 3);
        assert!(r.contains(5) && !r.contains(6) && !r.contains(9));
        let r: FrameRange = serde_json::from_str(r#"{"first": 4, "last": 4}"#).expect("object");
        assert_eq!(r.frames().collect::<Vec<_>>(), vec![4]);
        assert!(serde_json::from_str::<FrameRange>("\"a-b\"").is_err());
        assert!(serde_json::from_str::<FrameRange>(r#"{"first": 1}"#).is_err());
        assert!(
            "3-1"
                .parse::<FrameRange>()
                .expect("parses")
                .validate()
                .is_err()
        );
        assert!(
            "1-3:0"
                .parse::<FrameRange>()
                .expect("parses")
                .validate()
                .is_err()
        );
        assert!(
            "0-10000"
                .parse::<FrameRange>()
                .expect("parses")
                .validate()
                .is_err()
        );
        assert!(
            "1-10000"
                .parse::<FrameRange>()
                .expect("parses")
                .validate()
                .is_ok()
        );
    }

    #[test]
    fn frame_files_are_the_pattern_zero_padded() {
        assert_eq!(
            frame_file("frame_####.xml", 7).as_deref(),
            Some("frame_0007.xml")
        );
        assert_eq!(frame_file("a/f#.json", 12).as_deref(), Some("a/f12.json"));
        assert_eq!(frame_file("f##_#.json", 1), None);
        assert_eq!(frame_file("a#/f.json", 1), None);
        assert_eq!(frame_file("scene.json", 1), None);
        assert_eq!(frame_of("frame_####.xml", "frame_0012.xml"), Some(12));
        assert_eq!(frame_of("frame_####.xml", "frame_12.xml"), None);
        assert_eq!(frame_of("frame_##.xml", "frame_123.xml"), Some(123));
        assert_eq!(frame_of("frame_##.xml", "frame_012.xml"), None);
        assert_eq!(frame_of("frame_####.xml", "mesh.obj"), None);
        assert!(validate_pattern("frame_####.xml", "scene").is_ok());
        assert!(validate_pattern("frame.xml", "scene").is_err());
    }
}
