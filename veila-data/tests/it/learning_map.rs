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
    }
}
