use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::MAX_LEVEL;

/// Names one block: its level (0 = finest) and its integer coordinate on that
/// level's block grid. The text form `level-x-y-z` is what URLs and the manifest use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BlockKey {
    pub level: u8,
    pub x: u32,
    pub y: u32,
    pub z: u32,
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum KeyError {
    #[error("block key {0:?} is not of the form level-x-y-z")]
    Malformed(String),
    #[error("block key level {0} exceeds the maximum {MAX_LEVEL}")]
    LevelTooDeep(u32),
}

impl BlockKey {
    pub const fn new(level: u8, x: u32, y: u32, z: u32) -> Self {
        Self { level, x, y, z }
    }

    pub fn coord(&self) -> [u32; 3] {
        [self.x, self.y, self.z]
    }

    /// The block one level coarser that contains this one.
    pub fn parent(&self) -> BlockKey {
        BlockKey::new(self.level + 1, self.x / 2, self.y / 2, self.z / 2)
    }

    /// The eight blocks one level finer; `None` on level 0.
    pub fn children(&self) -> Option<[BlockKey; 8]> {
        if self.level == 0 {
            return None;
        }
        let l = self.level - 1;
        Some(std::array::from_fn(|i| {
            let i = i as u32;
            BlockKey::new(l, self.x * 2 + (i & 1), self.y * 2 + ((i >> 1) & 1), self.z * 2 + ((i >> 2) & 1))
        }))
    }
}

impl fmt::Display for BlockKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-{}-{}-{}", self.level, self.x, self.y, self.z)
    }
}

impl FromStr for BlockKey {
    type Err = KeyError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let malformed = || KeyError::Malformed(s.chars().take(64).collect());
        let mut parts = [0u32; 4];
        let mut n = 0;
        for part in s.split('-') {
            // Digits only: rejects signs, spaces, dots and anything path-like.
            if n == 4 || part.is_empty() || part.len() > 10 || !part.bytes().all(|b| b.is_ascii_digit()) {
                return Err(malformed());
            }
            parts[n] = part.parse().map_err(|_| malformed())?;
            n += 1;
        }
        if n != 4 {
            return Err(malformed());
        }
        if parts[0] > MAX_LEVEL as u32 {
            return Err(KeyError::LevelTooDeep(parts[0]));
        }
        Ok(BlockKey::new(parts[0] as u8, parts[1], parts[2], parts[3]))
    }
}

impl Serialize for BlockKey {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for BlockKey {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_round_trip() {
        let k = BlockKey::new(3, 0, 17, 4_000_000_000);
        assert_eq!(k.to_string(), "3-0-17-4000000000");
        assert_eq!(k.to_string().parse::<BlockKey>().unwrap(), k);
    }

    #[test]
    fn rejects_malformed() {
        for bad in [
            "",
            "1-2-3",
            "1-2-3-4-5",
            "a-1-2-3",
            "-1-2-3-4",
            "1--2-3",
            "../1-2-3",
            "1-2-3-4 ",
            "+1-2-3-4",
            "1-2-3-99999999999",
        ] {
            assert!(bad.parse::<BlockKey>().is_err(), "{bad:?} parsed");
        }
        assert_eq!("99-0-0-0".parse::<BlockKey>(), Err(KeyError::LevelTooDeep(99)));
    }

    #[test]
    fn parent_of_children_is_self() {
        let k = BlockKey::new(2, 3, 0, 5);
        for c in k.children().unwrap() {
            assert_eq!(c.parent(), k);
        }
        assert!(BlockKey::new(0, 1, 1, 1).children().is_none());
    }
}
