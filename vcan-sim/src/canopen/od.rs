//! A small object dictionary: entries keyed by (index, sub-index) with their size, access,
//! PDO mappability and value, and the SDO checks every entry gets (existence, access, size).
//! What a write *means* (PDO rules, accepted values, side effects) is the device's business
//! ([`super::device`]).

use rollbase_driver::canopen::sdo::{AbortCode, SdoData};

/// Access type of an entry (CiA 301).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Read only; the device may change it.
    Ro,
    /// Read and write.
    Rw,
    /// Write only.
    Wo,
    /// Read only, never changes.
    Const,
}

/// Whether an entry may be mapped into a PDO, and into which direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mappable {
    /// Not mappable.
    No,
    /// Into a TPDO (the device sends it).
    Tpdo,
    /// Into an RPDO (the device receives it).
    Rpdo,
}

/// One entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Entry {
    /// Size in bytes (1, 2 or 4).
    pub size: u8,
    /// Access type.
    pub access: Access,
    /// PDO mappability.
    pub map: Mappable,
    /// Current value (little-endian bytes as an integer, truncated to `size`).
    pub value: u32,
    /// Value after a reset.
    pub default: u32,
}

fn truncate(v: u32, size: u8) -> u32 {
    match size {
        1 => v & 0xFF,
        2 => v & 0xFFFF,
        _ => v,
    }
}

/// The dictionary: entries sorted by (index, sub), allocated once.
#[derive(Clone, Debug, Default)]
pub struct Dictionary {
    entries: Vec<((u16, u8), Entry)>,
}

impl Dictionary {
    /// An empty dictionary.
    pub fn new() -> Self {
        Self {
            entries: Vec::with_capacity(96),
        }
    }

    /// Adds (or replaces) an entry with `default` as its value.
    pub fn add(
        &mut self,
        index: u16,
        sub: u8,
        size: u8,
        access: Access,
        map: Mappable,
        default: u32,
    ) {
        let e = Entry {
            size,
            access,
            map,
            value: truncate(default, size),
            default: truncate(default, size),
        };
        match self
            .entries
            .binary_search_by_key(&(index, sub), |(k, _)| *k)
        {
            Ok(i) => self.entries[i].1 = e,
            Err(i) => self.entries.insert(i, ((index, sub), e)),
        }
    }

    /// The entry, if it exists.
    pub fn get(&self, index: u16, sub: u8) -> Option<&Entry> {
        self.entries
            .binary_search_by_key(&(index, sub), |(k, _)| *k)
            .ok()
            .map(|i| &self.entries[i].1)
    }

    /// True when any sub-index of `index` exists.
    pub fn has_index(&self, index: u16) -> bool {
        let i = self.entries.partition_point(|((ix, _), _)| *ix < index);
        self.entries.get(i).is_some_and(|((ix, _), _)| *ix == index)
    }

    /// The value (0 for a missing entry).
    pub fn value(&self, index: u16, sub: u8) -> u32 {
        self.get(index, sub).map_or(0, |e| e.value)
    }

    /// Sets a value without any check (the device's own updates); missing entries are
    /// ignored.
    pub fn set(&mut self, index: u16, sub: u8, v: u32) {
        if let Ok(i) = self
            .entries
            .binary_search_by_key(&(index, sub), |(k, _)| *k)
        {
            let e = &mut self.entries[i].1;
            e.value = truncate(v, e.size);
        }
    }

    /// Changes an existing entry's default (its value after power-on and resets) and its
    /// value; missing entries are ignored.
    pub fn set_default(&mut self, index: u16, sub: u8, v: u32) {
        if let Ok(i) = self
            .entries
            .binary_search_by_key(&(index, sub), |(k, _)| *k)
        {
            let e = &mut self.entries[i].1;
            e.default = truncate(v, e.size);
            e.value = e.default;
        }
    }

    /// Values back to their defaults for every index in `range`.
    pub fn reset(&mut self, range: std::ops::RangeInclusive<u16>) {
        for ((ix, _), e) in &mut self.entries {
            if range.contains(ix) {
                e.value = e.default;
            }
        }
    }

    fn find(&self, index: u16, sub: u8) -> Result<&Entry, AbortCode> {
        match self.get(index, sub) {
            Some(e) => Ok(e),
            None if self.has_index(index) => Err(AbortCode::NoSubIndex),
            None => Err(AbortCode::NoObject),
        }
    }

    /// An SDO upload: the value, or the abort code (object or sub-index missing, write-only).
    pub fn sdo_read(&self, index: u16, sub: u8) -> Result<SdoData, AbortCode> {
        let e = self.find(index, sub)?;
        if e.access == Access::Wo {
            return Err(AbortCode::WriteOnly);
        }
        Ok(SdoData::new(e.value, e.size))
    }

    /// The checks of an SDO download that do not depend on the object's meaning: it exists,
    /// it is writable, the data has its size. Returns the entry.
    pub fn sdo_check_write(&self, index: u16, sub: u8, data: &SdoData) -> Result<Entry, AbortCode> {
        let e = *self.find(index, sub)?;
        if matches!(e.access, Access::Ro | Access::Const) {
            return Err(AbortCode::ReadOnly);
        }
        match data.len().cmp(&usize::from(e.size)) {
            std::cmp::Ordering::Greater => Err(AbortCode::LengthMismatch),
            std::cmp::Ordering::Less => Err(AbortCode::LengthMismatch),
            std::cmp::Ordering::Equal => Ok(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sdo_checks() {
        let mut d = Dictionary::new();
        d.add(0x1017, 0, 2, Access::Rw, Mappable::No, 0);
        d.add(0x1000, 0, 4, Access::Const, Mappable::No, 0x0002_0192);
        d.add(0x2000, 0, 1, Access::Wo, Mappable::No, 0);
        assert_eq!(d.sdo_read(0x1000, 0).unwrap().as_u32(), 0x0002_0192);
        assert_eq!(d.sdo_read(0x1234, 0), Err(AbortCode::NoObject));
        assert_eq!(d.sdo_read(0x1000, 1), Err(AbortCode::NoSubIndex));
        assert_eq!(d.sdo_read(0x2000, 0), Err(AbortCode::WriteOnly));
        assert_eq!(
            d.sdo_check_write(0x1000, 0, &SdoData::u32(1)),
            Err(AbortCode::ReadOnly)
        );
        assert_eq!(
            d.sdo_check_write(0x1017, 0, &SdoData::u32(1)),
            Err(AbortCode::LengthMismatch)
        );
        assert!(d.sdo_check_write(0x1017, 0, &SdoData::u16(100)).is_ok());
        d.set(0x1017, 0, 0x12345);
        assert_eq!(d.value(0x1017, 0), 0x2345, "truncated to the entry's size");
        d.reset(0x1000..=0x1FFF);
        assert_eq!(d.value(0x1017, 0), 0);
    }
}
