//! What an import produced and what it left out ([`ImportReport`]).

use std::collections::BTreeMap;

use esrp_core::Scene;

/// What an import produced and what it left out.
#[derive(Clone, Debug, Default)]
pub struct ImportReport {
    /// The scene pairs, each validated and replayed to success, in house and room order.
    pub scenes: Vec<Scene>,
    /// House files read.
    pub houses: usize,
    /// Rooms seen.
    pub rooms_seen: usize,
    /// Rooms that became a scene.
    pub rooms_imported: usize,
    /// Rooms skipped, by reason (see [the `front` module](crate::front)).
    pub rooms_skipped: BTreeMap<String, usize>,
    /// Furniture objects dropped, by reason (see [the `front` module](crate::front)).
    pub objects_dropped: BTreeMap<String, usize>,
    /// Movable pieces moved apart from what they overlapped (in scenes that were imported).
    pub objects_nudged: usize,
    /// Carryable pieces kept fixed because no nudge freed them (in scenes that were imported).
    pub movable_overlapping: usize,
    /// Warnings: missing or unreadable models, floor fallbacks, ...
    pub warnings: Vec<String>,
}

impl ImportReport {
    pub(super) fn skip(&mut self, reason: &str) {
        *self.rooms_skipped.entry(reason.to_owned()).or_insert(0) += 1;
    }

    pub(super) fn drop_object(&mut self, reason: &str) {
        *self.objects_dropped.entry(reason.to_owned()).or_insert(0) += 1;
    }
}
