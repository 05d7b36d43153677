//! Plan geometry of a room: bounds, and the floor outline from the floor meshes' triangles.

use std::collections::{BTreeMap, HashMap};

use esrp_core::geometry::{PlanPoint, polygon_is_simple, signed_area};

pub(super) fn plan(p: [f64; 3]) -> PlanPoint {
    PlanPoint::new(p[0], p[2])
}

pub(super) fn bounds(points: impl IntoIterator<Item = [f64; 3]>) -> Option<([f64; 3], [f64; 3])> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut any = false;
    for p in points {
        any = true;
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    any.then_some((lo, hi))
}

/// Distance from `p` to segment `a`–`b` and the parameter of the closest point.
pub(super) fn segment_projection(p: PlanPoint, a: PlanPoint, b: PlanPoint) -> (f64, f64) {
    let (dx, dz) = (b.x - a.x, b.z - a.z);
    let length2 = dx * dx + dz * dz;
    let t = if length2 > 0.0 { ((p.x - a.x) * dx + (p.z - a.z) * dz) / length2 } else { 0.0 };
    let tc = t.clamp(0.0, 1.0);
    (p.distance(PlanPoint::new(a.x + tc * dx, a.z + tc * dz)), t)
}

/// The outline of the union of plan triangles as one counter-clockwise simple polygon, with
/// the number of outlines found; `None` if the largest outline is not a simple polygon.
pub(super) fn floor_outline(triangles: &[[PlanPoint; 3]]) -> Option<(Vec<PlanPoint>, usize)> {
    // Weld vertices to the millimetre.
    let mut ids: HashMap<(i64, i64), u32> = HashMap::new();
    let mut points: Vec<PlanPoint> = Vec::new();
    let mut weld = |p: PlanPoint| {
        let key = ((p.x * 1000.0).round() as i64, (p.z * 1000.0).round() as i64);
        *ids.entry(key).or_insert_with(|| {
            points.push(p);
            (points.len() - 1) as u32
        })
    };
    let mut welded: Vec<[u32; 3]> = Vec::new();
    for t in triangles {
        let mut w = [weld(t[0]), weld(t[1]), weld(t[2])];
        if w[0] == w[1] || w[1] == w[2] || w[0] == w[2] {
            continue;
        }
        let area = signed_area(&[t[0], t[1], t[2]]);
        if area.abs() < 1e-8 {
            continue;
        }
        if area < 0.0 {
            w.swap(1, 2);
        }
        welded.push(w);
    }
    // Directed edges, split where another vertex lies on them (T-junctions between meshes).
    let mut net: HashMap<(u32, u32), i32> = HashMap::new();
    for tri in &welded {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let (pa, pb) = (points[a as usize], points[b as usize]);
            let mut on: Vec<(f64, u32)> = (0..points.len() as u32)
                .filter(|&v| v != a && v != b)
                .filter_map(|v| {
                    let (d, t) = segment_projection(points[v as usize], pa, pb);
                    (d < 5e-4 && t > 1e-6 && t < 1.0 - 1e-6).then_some((t, v))
                })
                .collect();
            on.sort_by(|x, y| x.0.total_cmp(&y.0));
            let chain: Vec<u32> = std::iter::once(a).chain(on.into_iter().map(|(_, v)| v)).chain([b]).collect();
            for pair in chain.windows(2) {
                *net.entry((pair[0], pair[1])).or_insert(0) += 1;
                *net.entry((pair[1], pair[0])).or_insert(0) -= 1;
            }
        }
    }
    let mut boundary: Vec<(u32, u32)> = net.iter().filter(|(_, c)| **c > 0).map(|(e, _)| *e).collect();
    boundary.sort_unstable();
    let mut next: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for (a, b) in &boundary {
        next.entry(*a).or_default().push(*b);
    }
    let mut loops: Vec<Vec<PlanPoint>> = Vec::new();
    while let Some((&start, _)) = next.iter().find(|(_, v)| !v.is_empty()) {
        let mut ring = vec![start];
        let mut at = start;
        while let Some(to) = next.get_mut(&at).and_then(|v| v.pop()) {
            if to == start || ring.len() > boundary.len() {
                break;
            }
            ring.push(to);
            at = to;
        }
        loops.push(ring.into_iter().map(|v| points[v as usize]).collect());
    }
    let count = loops.len();
    let outline = loops.into_iter().max_by(|a, b| signed_area(a).total_cmp(&signed_area(b)))?;
    let outline = simplify_collinear(outline);
    (outline.len() >= 3 && signed_area(&outline) > 0.0 && polygon_is_simple(&outline)).then_some((outline, count))
}

/// Removes repeated points and points on the line through their neighbours (within 1 mm).
pub(super) fn simplify_collinear(mut polygon: Vec<PlanPoint>) -> Vec<PlanPoint> {
    let mut changed = true;
    while changed && polygon.len() > 3 {
        changed = false;
        let n = polygon.len();
        for i in 0..n {
            let (prev, here, next) = (polygon[(i + n - 1) % n], polygon[i], polygon[(i + 1) % n]);
            let (d, t) = segment_projection(here, prev, next);
            if here.distance(next) < 1e-3 || (d < 1e-3 && (0.0..=1.0).contains(&t)) {
                polygon.remove(i);
                changed = true;
                break;
            }
        }
    }
    polygon
}
