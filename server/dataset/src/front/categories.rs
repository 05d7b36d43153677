//! Which 3D-FUTURE categories are carryable, and as which ESRP category.

use esrp_core::MovableCategory;

/// The ESRP category of a 3D-FUTURE model by its `category` and `super-category` (or the
/// house file's own category or title), or `None` for furniture that is never carried (beds,
/// wardrobes, large sofas, dining tables, ceiling and wall lamps, ...). Size is checked apart.
pub fn movable_category(category: &str, super_category: &str) -> Option<MovableCategory> {
    let c = category.to_lowercase();
    let s = super_category.to_lowercase();
    let has = |words: &[&str]| words.iter().any(|w| c.contains(w));
    if has(&["stool", "pier", "ottoman"]) {
        return Some(MovableCategory::PierStool);
    }
    if has(&["armchair", "loveseat", "lazy sofa", "single sofa", "one-seat"]) {
        return Some(MovableCategory::Sofa);
    }
    if has(&["bed", "wardrobe", "sofa", "dining table", "bar", "pendant", "ceiling", "wall lamp"]) {
        return None;
    }
    if has(&["chair"]) {
        return Some(MovableCategory::Chair);
    }
    if has(&["cabinet", "shelf", "desk", "nightstand", "bookcase", "drawer", "chest", "tv stand", "sideboard"])
        || has(&["console", "dressing table"])
    {
        return Some(MovableCategory::CabinetShelfDesk);
    }
    if has(&["coffee table", "side table", "end table", "tea table", "plant", "flower", "vase"])
        || has(&["floor lamp", "table lamp"])
    {
        return Some(MovableCategory::Others);
    }
    match s.as_str() {
        "cabinet/shelf/desk" => Some(MovableCategory::CabinetShelfDesk),
        "chair" => Some(MovableCategory::Chair),
        "pier/stool" => Some(MovableCategory::PierStool),
        _ => None,
    }
}
