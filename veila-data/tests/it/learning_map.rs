//! The built-in SemanticKITTI learning map against the official `semantic-kitti.yaml`
//! shipped with the real sample data.

use std::path::Path;

use veila_data::semantic_kitti::{LabelMap, class};

#[test]
fn builtin_learning_map_matches_semantic_kitti_yaml() {
    let yaml = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/semantickitti/semantic-kitti.yaml");
    if !yaml.exists() {
        eprintln!("skipping: {} not found", yaml.display());
        return;
    }
    let map = LabelMap::read(&yaml).unwrap();
    assert_eq!(map.num_classes(), class::NUM_LEARNING_CLASSES);
    for raw in 0..=300u16 {
        assert_eq!(
            class::learning_id(raw),
            map.train_id(raw as u32),
            "raw id {raw}"
        );
        assert_eq!(
            class::in_learning_map(raw),
            map.learning_map.contains_key(&raw),
            "raw id {raw} listed"
        );
    }
    for (t, raw) in class::LEARNING_MAP_INV.iter().enumerate() {
        assert_eq!(
            map.learning_map_inv.get(&(t as u8)),
            Some(raw),
            "train id {t}"
        );
        assert_eq!(
            map.train_name(t as u8),
            Some(class::LEARNING_NAMES[t]),
            "train id {t}"
        );
    }
}
