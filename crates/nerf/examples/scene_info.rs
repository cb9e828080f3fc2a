fn main() {
    let dir = std::env::args().nth(1).expect("dir");
    let spherify = std::env::args().any(|a| a == "--spherify");
    let colmap = std::env::args().any(|a| a == "--colmap");
    let opts = nerf::data::scene::SceneOptions { spherify, format: colmap.then_some(nerf::data::scene::Format::Colmap), ..Default::default() };
    let s = nerf::data::scene::Scene::open(std::path::Path::new(&dir), &opts, 4).expect("open");
    println!("{:?} frames {} train {} test {} near {} far {} bound {} space {:?}", s.format, s.frames.len(), s.train.len(), s.test.len(), s.near, s.far, s.bound, s.space);
    for c in s.cameras(nerf::data::Split::Train).iter().take(3) { println!("{:?}", c); }
    let r: Vec<f32> = s.cameras(nerf::data::Split::Train).iter().map(|c| nerf::math::length(c.origin())).collect();
    println!("radii {:?}", &r[..r.len().min(10)]);
}
