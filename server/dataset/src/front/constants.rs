//! The numbers of an import: wall size, hull size, which pieces are carryable, the clearance a
//! movable piece keeps, which rooms are too small, and the tolerances of placing pieces.

/// Wall thickness of imported rooms, metres.
pub const WALL_THICKNESS: f64 = 0.12;
/// Wall height when the room's wall meshes give none in 2.2–4 m, metres.
pub const DEFAULT_WALL_HEIGHT: f64 = 2.8;
/// The most points of one object's convex hull.
pub const MAX_HULL_POINTS: usize = 64;
/// The largest footprint side of a carryable piece, metres.
pub const MAX_CARRY_SIZE: f64 = 1.2;
/// The greatest height of a carryable piece, metres.
pub const MAX_CARRY_HEIGHT: f64 = 1.3;
/// The clearance a movable piece keeps to walls and other objects in the target layout,
/// metres: twice esrp-core's collision margin.
pub const CLEARANCE: f64 = 0.02;
/// Rooms with less floor than this are skipped, m².
pub const MIN_FLOOR_AREA: f64 = 4.0;
/// Rooms with less floor than this outside the footprints of standing furniture are skipped,
/// m².
pub const MIN_FREE_FLOOR: f64 = 2.0;
/// An object whose lowest point is at most this above the floor stands on it, metres.
pub(super) const STANDING_TOLERANCE: f64 = 0.05;
/// Objects lower than this are flat (rugs) and dropped, metres.
pub(super) const FLAT_HEIGHT: f64 = 0.03;
/// Nudge distances tried for an overlapping movable piece, metres.
pub(super) const NUDGES: [f64; 7] = [0.03, 0.06, 0.1, 0.15, 0.2, 0.25, 0.3];
