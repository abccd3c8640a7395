use glam::Vec3;
use veila_metrics::nn::PointIndex;
fn cpu_ns() -> u64 { std::fs::read_to_string("/proc/thread-self/schedstat").unwrap().split_whitespace().next().unwrap().parse().unwrap() }
fn read(name: &str) -> Vec<Vec3> {
    let bytes = std::fs::read(format!("/work/shared/data/real/kitti/training/velodyne/{name}")).unwrap();
    bytes.chunks_exact(16).map(|c| { let f = |i: usize| f32::from_le_bytes([c[i], c[i+1], c[i+2], c[i+3]]); Vec3::new(f(0), f(4), f(8)) }).collect()
}
fn main() {
    let a = read("000000.bin"); let b = read("000001.bin");
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    pool.install(|| {
    for _ in 0..3 {
        let t = cpu_ns();
        let ib = PointIndex::build(&b, "b").unwrap();
        let tb = cpu_ns() - t;
        let ia = PointIndex::build(&a, "a").unwrap();
        let t = cpu_ns();
        let s1: f64 = ib.nearest_dist2_all(&a).iter().sum();
        let tq = cpu_ns() - t;
        let q: Vec<Vec3> = ia.points_in_leaf_order().collect();
        let t = cpu_ns();
        let s2: f64 = ib.nearest_dist2_all(&q).iter().sum();
        let tq2 = cpu_ns() - t;
        println!("cpu: build {:.1}ms query scan order {:.1}ms leaf order {:.1}ms {s1} {s2} {:?}", tb as f64/1e6, tq as f64/1e6, tq2 as f64/1e6, ib);
    }});
}
