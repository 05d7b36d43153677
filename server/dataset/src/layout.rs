//! Target layouts that look designed: a room plan (rectangle or L-shape) with doors and windows,
//! furnished by the rules of its room type — beds against a wall with nightstands beside them,
//! desks with their chairs, sofas facing a TV stand around a coffee table, dining tables ringed
//! by chairs, wardrobes and bookcases on walls, clear floor in front of doors — and a choice of
//! which pieces the agent must move.

use esrp_core::geometry::{OrientedRect, PlanPoint, clip_convex, convex_inside_polygon, signed_area};
use esrp_core::{
    AgentStart, Difficulty, FixedObject, Heading, MovableCategory, MovableObject, ObjectPose, Opening, OpeningKind,
    Room, SCENE_SCHEMA, Scene, Shape, Split,
};

use crate::catalogue::{Kind, Model, catalogue, of_kind};
use crate::dice::Dice;

/// Gap kept between furniture and walls, and between pieces, metres. Larger than the collision
/// margin so that every movable object starts clear.
const GAP: f64 = 0.03;
/// A whole room stays under this many triangles (rendering cost grows with triangles).
pub const TRIANGLE_BUDGET: usize = 3000;

/// The room types of 3D-FRONT used by the benchmark, with their number of scenes in
/// `esrp-bench-v1` (5,495 in all; 8 types above 100, MasterBedroom and LivingDiningRoom largest,
/// the top six above 80 %).
pub const ROOM_TYPES: [(&str, usize); 24] = [
    ("MasterBedroom", 1430),
    ("LivingDiningRoom", 1200),
    ("SecondBedroom", 760),
    ("Bedroom", 560),
    ("LivingRoom", 340),
    ("DiningRoom", 230),
    ("StudyRoom", 150),
    ("Library", 120),
    ("KidsRoom", 95),
    ("ElderlyRoom", 80),
    ("Kitchen", 75),
    ("Lounge", 65),
    ("NannyRoom", 50),
    ("CloakRoom", 45),
    ("Balcony", 45),
    ("Bathroom", 40),
    ("MasterBathroom", 35),
    ("SecondBathroom", 30),
    ("StorageRoom", 30),
    ("Hallway", 30),
    ("Aisle", 25),
    ("Corridor", 20),
    ("Terrace", 20),
    ("OtherRoom", 20),
];

/// A wall of the plan: edge `a → b` with its inward normal.
#[derive(Clone, Copy, Debug)]
struct Wall {
    a: PlanPoint,
    dir: PlanPoint,
    inward: PlanPoint,
    length: f64,
}

/// A piece of furniture placed in the target layout.
#[derive(Clone, Debug)]
pub struct Placed {
    /// The catalogue model.
    pub model: &'static Model,
    /// Where it stands.
    pub pose: ObjectPose,
    /// Its footprint (the model's box at the pose).
    pub footprint: OrientedRect,
}

/// A room being furnished.
#[derive(Clone, Debug)]
pub struct RoomPlan {
    /// Floor polygon, counter-clockwise in (x, z).
    pub floor: Vec<PlanPoint>,
    walls: Vec<Wall>,
    /// Doors and windows.
    pub openings: Vec<Opening>,
    keepout: Vec<OrientedRect>,
    /// Furniture placed so far.
    pub placed: Vec<Placed>,
    triangles: usize,
}

fn footprint_of(model: &Model, pose: &ObjectPose, grow: f64) -> OrientedRect {
    OrientedRect {
        center: pose.position(),
        half_x: model.depth() / 2.0 + grow,
        half_z: model.width() / 2.0 + grow,
        yaw: pose.yaw,
    }
}

fn overlaps(a: &OrientedRect, b: &OrientedRect) -> bool {
    let reach = a.half_x.hypot(a.half_z) + b.half_x.hypot(b.half_z);
    if a.center.distance(b.center) >= reach {
        return false;
    }
    signed_area(&clip_convex(&a.corners(), &b.corners())) > 1e-9
}

/// Yaw that points local +x along `v`.
fn yaw_towards(v: PlanPoint) -> f64 {
    (-v.z).atan2(v.x)
}

impl RoomPlan {
    /// A rectangle `width × depth`, or an L-shape when `notch` is given (the fractions of width
    /// and depth cut from one corner, chosen by `corner` in 0..4).
    pub fn new(width: f64, depth: f64, notch: Option<(f64, f64, usize)>) -> Self {
        let mut floor: Vec<PlanPoint> = match notch {
            None => vec![(0.0, 0.0), (width, 0.0), (width, depth), (0.0, depth)],
            Some((fx, fz, _)) => {
                let (cw, cd) = (width * fx, depth * fz);
                vec![
                    (0.0, 0.0),
                    (width, 0.0),
                    (width, depth - cd),
                    (width - cw, depth - cd),
                    (width - cw, depth),
                    (0.0, depth),
                ]
            }
        }
        .into_iter()
        .map(|(x, z)| PlanPoint::new(x, z))
        .collect();
        if let Some((_, _, corner)) = notch {
            // Mirror the notch into the chosen corner.
            for p in &mut floor {
                if corner & 1 == 1 {
                    p.x = width - p.x;
                }
                if corner & 2 == 2 {
                    p.z = depth - p.z;
                }
            }
        }
        if signed_area(&floor) < 0.0 {
            floor.reverse();
        }
        let n = floor.len();
        let walls = (0..n)
            .map(|i| {
                let (a, b) = (floor[i], floor[(i + 1) % n]);
                let length = a.distance(b);
                let dir = PlanPoint::new((b.x - a.x) / length, (b.z - a.z) / length);
                // Counter-clockwise in (x, z): the interior is to the left, (−dz, dx).
                Wall { a, dir, inward: PlanPoint::new(-dir.z, dir.x), length }
            })
            .collect();
        Self { floor, walls, openings: Vec::new(), keepout: Vec::new(), placed: Vec::new(), triangles: 0 }
    }

    /// Adds a door of `width` on a wall long enough, keeping the floor in front of it clear.
    pub fn add_door(&mut self, dice: &mut Dice, width: f64) -> bool {
        let candidates: Vec<usize> = (0..self.walls.len())
            .filter(|&i| self.walls[i].length >= width + 0.5 && !self.openings.iter().any(|o| o.wall == i))
            .collect();
        if candidates.is_empty() {
            return false;
        }
        let wall = *dice.pick(&candidates);
        let w = self.walls[wall];
        let offset = dice.uniform(0.2, w.length - width - 0.2);
        self.openings.push(Opening { kind: OpeningKind::Door, wall, offset, width, bottom: 0.0, top: 2.05 });
        let centre = offset + width / 2.0;
        let depth = 0.9;
        self.keepout.push(OrientedRect {
            center: PlanPoint::new(
                w.a.x + w.dir.x * centre + w.inward.x * depth / 2.0,
                w.a.z + w.dir.z * centre + w.inward.z * depth / 2.0,
            ),
            half_x: depth / 2.0,
            half_z: width / 2.0 + 0.1,
            yaw: yaw_towards(w.inward),
        });
        true
    }

    /// Adds a window on a wall that has no door and is long enough.
    pub fn add_window(&mut self, dice: &mut Dice) {
        let free: Vec<usize> = (0..self.walls.len())
            .filter(|&i| self.walls[i].length >= 1.6 && !self.openings.iter().any(|o| o.wall == i))
            .collect();
        if free.is_empty() {
            return;
        }
        let wall = *dice.pick(&free);
        let length = self.walls[wall].length;
        let width = dice.uniform(0.8, (length - 0.6).min(2.0));
        let offset = dice.uniform(0.3, length - width - 0.3);
        self.openings.push(Opening { kind: OpeningKind::Window, wall, offset, width, bottom: 0.9, top: 2.1 });
    }

    fn fits(&self, model: &Model, pose: &ObjectPose) -> bool {
        if self.triangles + model.triangle_estimate() > TRIANGLE_BUDGET {
            return false;
        }
        let exact = footprint_of(model, pose, 0.0);
        // Inside the room with a gap to the walls, clear of doors and of other pieces.
        if !convex_inside_polygon(&footprint_of(model, pose, GAP).corners(), &self.floor) {
            return false;
        }
        let grown = footprint_of(model, pose, GAP);
        !self.keepout.iter().any(|k| overlaps(k, &exact)) && !self.placed.iter().any(|p| overlaps(&p.footprint, &grown))
    }

    /// Places `model` at `pose` if it fits; returns its index.
    pub fn place(&mut self, model: &'static Model, pose: ObjectPose) -> Option<usize> {
        if !self.fits(model, &pose) {
            return None;
        }
        self.triangles += model.triangle_estimate();
        self.placed.push(Placed { model, pose, footprint: footprint_of(model, &pose, 0.0) });
        Some(self.placed.len() - 1)
    }

    /// Places `model` with its back against a wall (a random one if `wall` is `None`), at the
    /// fraction `at` of the wall's free length (random if `None`). Tries a few times.
    pub fn against_wall(
        &mut self,
        dice: &mut Dice,
        model: &'static Model,
        wall: Option<usize>,
        at: Option<f64>,
    ) -> Option<usize> {
        for attempt in 0..12 {
            // The requested wall and spot first, then jittered spots on it, then any wall.
            let index = match wall {
                Some(w) if attempt < 8 => w,
                _ => dice.below(self.walls.len()),
            };
            let w = self.walls[index];
            let half = model.width() / 2.0 + GAP;
            if w.length < 2.0 * half {
                continue;
            }
            let t = match at {
                Some(t) if attempt == 0 => t,
                Some(t) if attempt < 8 => (t + dice.uniform(-0.2, 0.2)).clamp(0.0, 1.0),
                _ => dice.unit(),
            };
            let u = half + t * (w.length - 2.0 * half);
            let inset = model.depth() / 2.0 + GAP + 0.005;
            let pose = ObjectPose::new(
                w.a.x + w.dir.x * u + w.inward.x * inset,
                w.a.z + w.dir.z * u + w.inward.z * inset,
                yaw_towards(w.inward),
            );
            if let Some(i) = self.place(model, pose) {
                return Some(i);
            }
        }
        None
    }

    /// The pose `forward` metres along piece `anchor`'s local +x (its front) and `side` metres
    /// along its local +z, with the anchor's yaw turned by `turn`.
    fn relative(&self, anchor: usize, forward: f64, side: f64, turn: f64) -> ObjectPose {
        let a = &self.placed[anchor].pose;
        let (s, c) = a.yaw.sin_cos();
        ObjectPose::new(a.x + c * forward + s * side, a.z - s * forward + c * side, a.yaw + turn)
    }

    /// Places `model` beside piece `anchor`, aligned with it (same facing, backs level), on
    /// the side `sign` (±1 along the anchor's local z).
    pub fn beside(&mut self, anchor: usize, model: &'static Model, sign: f64) -> Option<usize> {
        let a = self.placed[anchor].model;
        let side = sign * (a.width() / 2.0 + model.width() / 2.0 + GAP + 0.02);
        let forward = -(a.depth() - model.depth()) / 2.0;
        let pose = self.relative(anchor, forward, side, 0.0);
        self.place(model, pose)
    }

    /// Places `model` in front of piece `anchor` at `gap` metres, facing it when `facing`,
    /// otherwise facing the same way.
    pub fn in_front(&mut self, anchor: usize, model: &'static Model, gap: f64, facing: bool) -> Option<usize> {
        let a = self.placed[anchor].model;
        let forward = a.depth() / 2.0 + gap + model.depth() / 2.0;
        let turn = if facing { std::f64::consts::PI } else { 0.0 };
        let pose = self.relative(anchor, forward, 0.0, turn);
        self.place(model, pose)
    }

    /// Places up to `count` chairs around table `anchor`, each facing the table.
    pub fn around(&mut self, anchor: usize, model: &'static Model, count: usize) -> usize {
        let t = self.placed[anchor].model;
        let (d, w) = (t.depth() / 2.0, t.width() / 2.0);
        let tuck = model.depth() / 2.0 + 0.1;
        // Chairs along the long sides first (local ±x faces), then the ends (±z).
        let mut seats = Vec::new();
        let per_side = if w > 0.8 { 3 } else { 2 };
        for side in [1.0, -1.0] {
            for k in 0..per_side {
                let along = -w + (2.0 * w) * (k as f64 + 0.5) / per_side as f64;
                seats.push((side * (d + tuck), along, if side > 0.0 { std::f64::consts::PI } else { 0.0 }));
            }
        }
        for side in [1.0, -1.0] {
            seats.push((0.0, side * (w + tuck), side * std::f64::consts::FRAC_PI_2));
        }
        let mut placed = 0;
        for (forward, side, turn) in seats {
            if placed == count {
                break;
            }
            let pose = self.relative(anchor, forward, side, turn);
            if self.place(model, pose).is_some() {
                placed += 1;
            }
        }
        placed
    }

    /// Places `model` anywhere it fits, turned to a wall direction (free-standing pieces).
    pub fn anywhere(&mut self, dice: &mut Dice, model: &'static Model) -> Option<usize> {
        let (lo, hi) = bounds(&self.floor);
        for _ in 0..20 {
            let yaw = dice.below(4) as f64 * std::f64::consts::FRAC_PI_2 + dice.uniform(-0.2, 0.2);
            let pose = ObjectPose::new(dice.uniform(lo.x, hi.x), dice.uniform(lo.z, hi.z), yaw);
            if let Some(i) = self.place(model, pose) {
                return Some(i);
            }
        }
        None
    }

    /// The number of walls.
    pub fn wall_count(&self) -> usize {
        self.walls.len()
    }

    /// The index of the longest wall.
    pub fn longest_wall(&self) -> usize {
        (0..self.walls.len()).max_by(|&a, &b| self.walls[a].length.total_cmp(&self.walls[b].length)).unwrap_or(0)
    }

    /// The wall facing wall `i` most directly (inward normals most opposed).
    pub fn opposite_wall(&self, i: usize) -> usize {
        let n = self.walls[i].inward;
        (0..self.walls.len())
            .filter(|&j| j != i)
            .min_by(|&a, &b| {
                let da = self.walls[a].inward.x * n.x + self.walls[a].inward.z * n.z;
                let db = self.walls[b].inward.x * n.x + self.walls[b].inward.z * n.z;
                da.total_cmp(&db)
            })
            .unwrap_or(i)
    }
}

fn bounds(points: &[PlanPoint]) -> (PlanPoint, PlanPoint) {
    let mut lo = PlanPoint::new(f64::MAX, f64::MAX);
    let mut hi = PlanPoint::new(f64::MIN, f64::MIN);
    for p in points {
        lo = PlanPoint::new(lo.x.min(p.x), lo.z.min(p.z));
        hi = PlanPoint::new(hi.x.max(p.x), hi.z.max(p.z));
    }
    (lo, hi)
}

fn pick_kind(dice: &mut Dice, kind: Kind) -> &'static Model {
    let models: Vec<&'static Model> = of_kind(kind).collect();
    models[dice.below(models.len())]
}

fn named(name: &str) -> &'static Model {
    catalogue().iter().find(|m| m.name == name).unwrap_or(&catalogue()[0])
}

/// Room size ranges `(width, depth)` and the chance of an L-shape, by room family.
fn room_size(dice: &mut Dice, room_type: &str) -> (f64, f64, f64) {
    let (w, d, l) = match room_type {
        "MasterBedroom" => ((4.0, 5.6), (3.8, 5.0), 0.25),
        "SecondBedroom" | "Bedroom" | "KidsRoom" | "ElderlyRoom" | "NannyRoom" => ((3.4, 4.8), (3.4, 4.6), 0.2),
        "LivingDiningRoom" => ((6.0, 8.0), (4.2, 6.0), 0.35),
        "LivingRoom" | "Lounge" => ((4.6, 6.4), (4.0, 5.6), 0.25),
        "DiningRoom" => ((3.8, 5.2), (3.6, 4.8), 0.15),
        "StudyRoom" | "Library" => ((3.4, 4.8), (3.4, 4.6), 0.2),
        "Kitchen" => ((3.4, 4.6), (3.2, 4.4), 0.2),
        "Bathroom" | "MasterBathroom" | "SecondBathroom" => ((3.2, 4.2), (3.0, 4.0), 0.1),
        "CloakRoom" | "StorageRoom" => ((3.2, 4.4), (3.0, 4.0), 0.1),
        "Balcony" | "Terrace" => ((4.0, 6.5), (2.6, 3.4), 0.1),
        "Hallway" | "Aisle" | "Corridor" => ((4.5, 7.0), (2.2, 2.8), 0.0),
        _ => ((3.6, 5.2), (3.4, 4.8), 0.2),
    };
    (dice.uniform(w.0, w.1), dice.uniform(d.0, d.1), l)
}

/// Furnishes `plan` by the rules of `room_type`.
fn furnish(plan: &mut RoomPlan, dice: &mut Dice, room_type: &str) {
    match room_type {
        "MasterBedroom" | "SecondBedroom" | "Bedroom" | "KidsRoom" | "ElderlyRoom" | "NannyRoom" => {
            bedroom(plan, dice, room_type)
        }
        "LivingRoom" | "Lounge" => living(plan, dice, false),
        "LivingDiningRoom" => living(plan, dice, true),
        "DiningRoom" => dining(plan, dice),
        "StudyRoom" | "Library" => study(plan, dice, room_type == "Library"),
        "Kitchen" => kitchen(plan, dice),
        "Bathroom" | "MasterBathroom" | "SecondBathroom" => bathroom(plan, dice),
        "CloakRoom" | "StorageRoom" => storage(plan, dice),
        "Balcony" | "Terrace" => outdoor(plan, dice),
        "Hallway" | "Aisle" | "Corridor" => hallway(plan, dice),
        _ => other(plan, dice),
    }
}

fn bedroom(plan: &mut RoomPlan, dice: &mut Dice, room_type: &str) {
    let bed = match room_type {
        "MasterBedroom" => named(if dice.chance(0.5) { "bed_queen" } else { "bed_double" }),
        "KidsRoom" | "NannyRoom" | "ElderlyRoom" => named("bed_single"),
        _ => named(if dice.chance(0.6) { "bed_double" } else { "bed_single" }),
    };
    let bed_wall = plan.longest_wall();
    let centre = dice.uniform(0.3, 0.7);
    let bed_index =
        plan.against_wall(dice, bed, Some(bed_wall), Some(centre)).or_else(|| plan.against_wall(dice, bed, None, None));
    if let Some(b) = bed_index {
        let stand = pick_kind(dice, Kind::Nightstand);
        let sides: &[f64] = if room_type == "MasterBedroom" || dice.chance(0.5) { &[1.0, -1.0] } else { &[1.0] };
        for &side in sides {
            plan.beside(b, stand, side);
        }
        if dice.chance(0.35) {
            plan.in_front(b, pick_kind(dice, Kind::Stool), 0.15, false);
        }
    }
    let wardrobe = pick_kind(dice, Kind::Wardrobe);
    plan.against_wall(dice, wardrobe, Some(plan.opposite_wall(bed_wall)), None)
        .or_else(|| plan.against_wall(dice, wardrobe, None, None));
    if dice.chance(0.6) {
        let desk = pick_kind(dice, Kind::Desk);
        if let Some(d) = plan.against_wall(dice, desk, None, None) {
            plan.in_front(d, pick_kind(dice, Kind::Chair), 0.1, true);
        }
    }
    for kind in [Kind::Cabinet, Kind::Armchair, Kind::Plant, Kind::Lamp, Kind::Shelf] {
        if dice.chance(0.45) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn living(plan: &mut RoomPlan, dice: &mut Dice, with_dining: bool) {
    let sofa_wall = plan.longest_wall();
    let at = if with_dining { dice.uniform(0.15, 0.35) } else { dice.uniform(0.35, 0.65) };
    let sofa = pick_kind(dice, Kind::Sofa);
    if let Some(s) = plan.against_wall(dice, sofa, Some(sofa_wall), Some(at)) {
        plan.in_front(s, named("coffee_table"), 0.45, false);
        let table = pick_kind(dice, Kind::SideTable);
        plan.beside(s, table, if dice.chance(0.5) { 1.0 } else { -1.0 });
        // Armchairs across the coffee table, facing the sofa.
        if dice.chance(0.7) {
            plan.in_front(s, pick_kind(dice, Kind::Armchair), 1.6, true);
        }
        let opposite = plan.opposite_wall(sofa_wall);
        let tv = pick_kind(dice, Kind::TvStand);
        plan.against_wall(dice, tv, Some(opposite), Some(1.0 - at));
    }
    if with_dining {
        dining_group(plan, dice, 0.75);
    }
    for kind in [Kind::Bookcase, Kind::Shelf, Kind::Cabinet, Kind::Plant, Kind::Plant, Kind::Lamp, Kind::Stool] {
        if dice.chance(0.45) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

/// A dining table, free-standing at about `at` along the room's long axis, ringed by chairs.
fn dining_group(plan: &mut RoomPlan, dice: &mut Dice, at: f64) {
    let (lo, hi) = bounds(&plan.floor);
    let table = pick_kind(dice, Kind::DiningTable);
    let chair = pick_kind(dice, Kind::Chair);
    for _ in 0..12 {
        let along_x = hi.x - lo.x >= hi.z - lo.z;
        let (x, z) = if along_x {
            (lo.x + (hi.x - lo.x) * (at + dice.uniform(-0.1, 0.1)), lo.z + (hi.z - lo.z) * dice.uniform(0.35, 0.65))
        } else {
            (lo.x + (hi.x - lo.x) * dice.uniform(0.35, 0.65), lo.z + (hi.z - lo.z) * (at + dice.uniform(-0.1, 0.1)))
        };
        let yaw = if dice.chance(0.5) { 0.0 } else { std::f64::consts::FRAC_PI_2 };
        if let Some(t) = plan.place(table, ObjectPose::new(x, z, yaw)) {
            let seats = if table.width() > 1.5 { 6 } else { 4 };
            plan.around(t, chair, seats);
            break;
        }
    }
}

fn dining(plan: &mut RoomPlan, dice: &mut Dice) {
    dining_group(plan, dice, 0.5);
    for kind in [Kind::Cabinet, Kind::Cabinet, Kind::Plant, Kind::Shelf, Kind::Lamp] {
        if dice.chance(0.5) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn study(plan: &mut RoomPlan, dice: &mut Dice, library: bool) {
    let desk = if dice.chance(0.5) { named("desk_large") } else { pick_kind(dice, Kind::Desk) };
    if let Some(d) = plan.against_wall(dice, desk, None, None) {
        let chair = if dice.chance(0.6) { named("chair_office") } else { pick_kind(dice, Kind::Chair) };
        plan.in_front(d, chair, 0.1, true);
    }
    for _ in 0..if library { 3 } else { 1 } {
        let m = pick_kind(dice, Kind::Bookcase);
        plan.against_wall(dice, m, None, None);
    }
    if dice.chance(0.6) {
        let armchair = pick_kind(dice, Kind::Armchair);
        if let Some(a) = plan.against_wall(dice, armchair, None, None) {
            plan.beside(a, pick_kind(dice, Kind::SideTable), 1.0);
        }
    }
    for kind in [Kind::Shelf, Kind::Cabinet, Kind::Plant, Kind::Lamp] {
        if dice.chance(0.5) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn kitchen(plan: &mut RoomPlan, dice: &mut Dice) {
    let long = plan.longest_wall();
    if let Some(c) = plan.against_wall(dice, named("kitchen_counter_long"), Some(long), None) {
        plan.beside(c, named("fridge"), if dice.chance(0.5) { 1.0 } else { -1.0 });
    }
    if dice.chance(0.5) {
        plan.against_wall(dice, named("kitchen_counter_short"), None, None);
    }
    let table = pick_kind(dice, Kind::SideTable);
    if let Some(t) = plan.anywhere(dice, table) {
        plan.around(t, pick_kind(dice, Kind::Stool), 2);
    }
    for kind in [Kind::Cabinet, Kind::Plant, Kind::Shelf] {
        if dice.chance(0.5) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn bathroom(plan: &mut RoomPlan, dice: &mut Dice) {
    let end = if dice.chance(0.5) { 0.0 } else { 1.0 };
    plan.against_wall(dice, named("bathtub"), Some(plan.longest_wall()), Some(end));
    plan.against_wall(dice, named("vanity"), None, None);
    plan.against_wall(dice, named("toilet"), None, None);
    for kind in [Kind::Stool, Kind::Cabinet, Kind::Plant, Kind::Shelf] {
        if dice.chance(0.5) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn storage(plan: &mut RoomPlan, dice: &mut Dice) {
    for _ in 0..2 {
        let m = pick_kind(dice, Kind::Wardrobe);
        plan.against_wall(dice, m, None, None);
    }
    for kind in [Kind::Shelf, Kind::Shelf, Kind::Cabinet, Kind::Stool, Kind::Cabinet] {
        if dice.chance(0.6) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn outdoor(plan: &mut RoomPlan, dice: &mut Dice) {
    let table = pick_kind(dice, Kind::SideTable);
    if let Some(t) = plan.anywhere(dice, table) {
        plan.around(t, pick_kind(dice, Kind::Chair), 2);
    }
    for kind in [Kind::Plant, Kind::Plant, Kind::Armchair, Kind::Stool, Kind::Plant] {
        if dice.chance(0.6) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn hallway(plan: &mut RoomPlan, dice: &mut Dice) {
    for kind in [Kind::Cabinet, Kind::Shelf, Kind::Stool, Kind::Plant, Kind::Plant, Kind::Lamp] {
        if dice.chance(0.55) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

fn other(plan: &mut RoomPlan, dice: &mut Dice) {
    for kind in [Kind::Bookcase, Kind::Cabinet, Kind::Armchair, Kind::Desk, Kind::Chair, Kind::Plant, Kind::Stool] {
        if dice.chance(0.5) {
            let m = pick_kind(dice, kind);
            plan.against_wall(dice, m, None, None);
        }
    }
}

/// The share of movable objects per category in the paper's benchmark (its counts: 3,718 /
/// 1,721 / 453 / 298 / 772), used to weight which pieces become movable.
pub const CATEGORY_SHARES: [(MovableCategory, f64); 5] = [
    (MovableCategory::CabinetShelfDesk, 3718.0),
    (MovableCategory::Chair, 1721.0),
    (MovableCategory::Sofa, 453.0),
    (MovableCategory::PierStool, 298.0),
    (MovableCategory::Others, 772.0),
];

/// How often rooms offer each category, measured on generated rooms: the selection weight
/// divides the target share by it so that the chosen objects follow [`CATEGORY_SHARES`].
const CATEGORY_SUPPLY: [(MovableCategory, f64); 5] = [
    (MovableCategory::CabinetShelfDesk, 0.85),
    (MovableCategory::Chair, 0.88),
    (MovableCategory::Sofa, 0.74),
    (MovableCategory::PierStool, 0.74),
    (MovableCategory::Others, 2.2),
];

fn category_weight(category: MovableCategory) -> f64 {
    let share = CATEGORY_SHARES.iter().find(|(c, _)| *c == category).map_or(1.0, |(_, w)| *w);
    let supply = CATEGORY_SUPPLY.iter().find(|(c, _)| *c == category).map_or(1.0, |(_, s)| *s);
    share / supply
}

/// Why a target layout could not be made.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum LayoutFailure {
    /// Fewer carryable pieces fit than the scene needs.
    TooFewMovable,
}

/// A furnished target layout with `movable_count` pieces chosen to be moved, as a scene whose
/// movable objects all stand at their targets (the start of backward construction), with the
/// agent not yet placed.
///
/// Rooms grow with the number of objects to move (a room with six pieces to rearrange needs
/// floor to carry them about), and by `ease` (0 at first, raised by the caller after rejected
/// attempts) so that a hard combination still yields a scene.
pub fn target_layout(
    dice: &mut Dice,
    room_type: &str,
    movable_count: usize,
    ease: f64,
) -> Result<Scene, LayoutFailure> {
    let (width, depth, l_chance) = room_size(dice, room_type);
    let scale = 1.0 + 0.06 * movable_count.saturating_sub(1) as f64 + 0.08 * ease;
    let (width, depth) = (width * scale, depth * scale);
    let notch = dice.chance(l_chance).then(|| (dice.uniform(0.25, 0.4), dice.uniform(0.25, 0.4), dice.below(4)));
    let mut plan = RoomPlan::new(width, depth, notch);
    plan.add_door(dice, 0.9);
    if plan.wall_count() > 4 && dice.chance(0.3) {
        plan.add_door(dice, 0.8);
    }
    plan.add_window(dice);
    if dice.chance(0.4) {
        plan.add_window(dice);
    }
    furnish(&mut plan, dice, room_type);

    // Choose the pieces to move, weighted by the benchmark's category shares.
    let mut candidates: Vec<usize> =
        (0..plan.placed.len()).filter(|&i| plan.placed[i].model.movable.is_some()).collect();
    // Top up with carryable accessories where the room is too sparse.
    let carryable: Vec<&'static Model> = catalogue().iter().filter(|m| m.movable.is_some()).collect();
    let mut tries = 0;
    while candidates.len() < movable_count + 1 && tries < 24 {
        tries += 1;
        let weights: Vec<f64> = carryable.iter().map(|m| m.movable.map_or(0.0, category_weight)).collect();
        let m = carryable[dice.weighted(&weights)];
        if let Some(i) = plan.against_wall(dice, m, None, None).or_else(|| plan.anywhere(dice, m)) {
            candidates.push(i);
        }
    }
    if candidates.len() < movable_count {
        return Err(LayoutFailure::TooFewMovable);
    }
    let mut chosen = Vec::with_capacity(movable_count);
    for _ in 0..movable_count {
        let weights: Vec<f64> = candidates
            .iter()
            .map(|&i| {
                let m = plan.placed[i].model;
                m.movable.map_or(0.0, category_weight) / of_category_count(m)
            })
            .collect();
        let pick = dice.weighted(&weights);
        chosen.push(candidates.swap_remove(pick));
    }
    chosen.sort_unstable();

    let mut fixed_objects = Vec::new();
    let mut movable_objects = Vec::new();
    for (i, p) in plan.placed.iter().enumerate() {
        let shape = Shape::Parts(p.model.parts.clone());
        if let Some(category) = p.model.movable.filter(|_| chosen.contains(&i)) {
            movable_objects.push(MovableObject {
                id: format!("{}-{}", p.model.category, i),
                category,
                model: p.model.name.to_owned(),
                shape,
                pose: p.pose,
                target: p.pose,
            });
        } else {
            fixed_objects.push(FixedObject {
                id: format!("{}-{}", p.model.category, i),
                category: p.model.category.to_owned(),
                model: p.model.name.to_owned(),
                shape,
                pose: p.pose,
            });
        }
    }
    Ok(Scene {
        schema: SCENE_SCHEMA.to_owned(),
        id: String::new(),
        room_type: room_type.to_owned(),
        difficulty: Difficulty::for_object_count(movable_count).unwrap_or(Difficulty::Hard),
        split: Split::Train,
        room: Room {
            floor: plan.floor.iter().map(|p| [p.x, p.z]).collect(),
            wall_height: 2.6,
            wall_thickness: 0.12,
            openings: plan.openings.clone(),
        },
        fixed_objects,
        movable_objects,
        agent: AgentStart { x: 0.0, z: 0.0, heading: Heading::default() },
        horizon: 200,
        expert_trajectory: Vec::new(),
    })
}

/// How many catalogue models share a model's category: weights are per category, not per model.
fn of_category_count(model: &Model) -> f64 {
    catalogue().iter().filter(|m| m.movable.is_some() && m.movable == model.movable).count().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn room_type_counts_match_the_benchmark() {
        let total: usize = ROOM_TYPES.iter().map(|(_, n)| n).sum();
        assert_eq!(total, 5495);
        assert_eq!(ROOM_TYPES.iter().filter(|(_, n)| *n > 100).count(), 8);
        let top6: usize = ROOM_TYPES[..6].iter().map(|(_, n)| n).sum();
        assert!(top6 as f64 / total as f64 > 0.8);
    }

    #[test]
    fn l_shapes_are_simple_counter_clockwise_polygons() {
        for corner in 0..4 {
            let plan = RoomPlan::new(5.0, 4.0, Some((0.3, 0.4, corner)));
            assert_eq!(plan.floor.len(), 6);
            assert!(signed_area(&plan.floor) > 0.0);
            assert!((signed_area(&plan.floor) - (20.0 - 1.5 * 1.6)).abs() < 1e-9);
            assert!(esrp_core::geometry::polygon_is_simple(&plan.floor));
        }
    }

    #[test]
    fn bedrooms_have_a_bed_against_a_wall_with_nightstands() {
        let mut beds = 0;
        for seed in 0..20 {
            let mut dice = Dice::new(seed, 0, 0);
            let scene = target_layout(&mut dice, "MasterBedroom", 1, 0.0).unwrap();
            if let Some(bed) = scene.fixed_objects.iter().find(|o| o.category == "bed") {
                beds += 1;
                let stands = scene
                    .fixed_objects
                    .iter()
                    .map(|o| (&o.category, o.pose))
                    .chain(scene.movable_objects.iter().map(|o| (&o.model, o.pose)))
                    .filter(|(c, p)| c.contains("nightstand") && p.position().distance(bed.pose.position()) < 1.6)
                    .count();
                assert!(stands >= 1, "seed {seed}: no nightstand beside the bed");
            }
        }
        assert!(beds >= 18, "{beds} of 20 master bedrooms got a bed");
    }
}
