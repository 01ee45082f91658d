//! Selection on a density built on purpose so that the paper's guided rule matches the volume
//! with a body-wall component that does not touch the nodule: the miss must be reported as
//! one (Dice 0, no hit, a "MISS" verdict), and the oracle must still see the nodule.

use aret_pipe::kernels::localization::ground_truth_on_grid;
use aret_pipe::stage::select::{
    centres, verdict, Analysis, BlobParams, Centre, Centres, Localize, Params as SelectParams, Rule, Search, Sizing,
    TieBreak, Weighed,
};

/// The blob search with `blob`'s keys.
fn blob_search(blob: BlobParams) -> SelectParams {
    SelectParams { blob, ..SelectParams::default() }
}

/// The centres `params` finds in `density` with the whole lattice as its lung field, the guided
/// search at an annotated diameter of 18 mm.
fn centres_in(
    params: &SelectParams,
    density: &Volume<f32>,
    judge: &(dyn Fn(Search, &Centre) -> Weighed + Sync),
) -> Centres {
    let lungs = vec![true; density.geometry.len()];
    let blobs = aret_pipe::stage::blobs::search(&params.blob.search(), density, Some(&lungs), Some(18.0));
    centres(params, &density.geometry, Some(&blobs), [0.0; 3], None, judge)
}

/// A search that takes the strongest blob it accepts anywhere in the lungs: no tie-break, no
/// fallback.
fn strongest() -> BlobParams {
    BlobParams {
        inside_mm: 0.0,
        tie_break: TieBreak::Response,
        blind_tie_break: TieBreak::Response,
        guided_fallback: false,
        guided_faint_ratio: 0.0,
        ..BlobParams::default()
    }
}
use aret_pipe::stage::sweep::{equivalent_diameter_mm, levels, Params, Region, Score};
use aret_pipe::volume::{Geometry, Volume};

fn geometry(dims: [usize; 3], spacing: f64, origin: f64) -> Geometry {
    Geometry {
        dims,
        spacing_mm: [spacing; 3],
        origin_mm: [origin; 3],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    }
}

/// Density on a 40³ grid of 2 mm cells: faint lung (0.1) everywhere, a dense body-wall bulge
/// on the x = 0 face (1.0 at the face, falling off: every size at some threshold), and a
/// fainter nodule at the centre (0.5), blurred by the reconstruction to a radius of 11 mm
/// where the truth has 7 mm — so its candidate reads 22 mm against the annotated 14 mm.
fn scene() -> Volume<f32> {
    let g = geometry([40; 3], 2.0, 1.0);
    let mut data = vec![0.1f32; g.len()];
    for z in 0..40 {
        for y in 0..40 {
            for x in 0..40 {
                let p = g.voxel_to_patient_mm([x as f64, y as f64, z as f64]);
                let wall = ((p[0] - 1.0).powi(2) + (p[1] - 20.0).powi(2) + (p[2] - 20.0).powi(2)).sqrt();
                let nodule = ((p[0] - 41.0).powi(2) + (p[1] - 41.0).powi(2) + (p[2] - 41.0).powi(2)).sqrt();
                let v = &mut data[x + 40 * (y + 40 * z)];
                if wall < 16.0 {
                    *v = (1.0 - wall / 32.0) as f32;
                }
                if nodule <= 11.0 {
                    *v = 0.5;
                }
            }
        }
    }
    Volume { geometry: g, data }
}

/// The paper's sweep: σ itself, percentiles of the whole box.
fn paper_sweep() -> Params {
    Params { score: Score::Density, region: Region::Box, ..Params::default() }
}

/// The consensus mask of the nodule on a 1 mm CT grid.
fn nodule_mask() -> Volume<u8> {
    let g = geometry([82; 3], 1.0, 0.0);
    let data = (0..g.len())
        .map(|i| {
            let p = g.voxel_to_patient_mm([(i % 82) as f64, ((i / 82) % 82) as f64, (i / 6724) as f64]);
            u8::from(((p[0] - 41.0).powi(2) + (p[1] - 41.0).powi(2) + (p[2] - 41.0).powi(2)).sqrt() <= 7.0)
        })
        .collect();
    Volume { geometry: g, data }
}

#[test]
fn a_guided_match_on_the_body_wall_is_reported_as_a_miss() {
    let density = scene();
    let levels = levels(&density, &paper_sweep()).unwrap();
    let gt = ground_truth_on_grid(&nodule_mask(), &density.geometry).unwrap();
    let analysis = Analysis::new(&levels, Some(&gt), &density.geometry);
    // The annotated diameter is the nodule's (14 mm); the wall bulge has a size closer to it
    // than the nodule's blurred blob (22 mm), so the guided rule takes the wall.
    let guided = analysis.describe(Rule::Guided, analysis.choose(Rule::Guided, Some(14.0), None).unwrap());
    assert!(guided.candidate.centroid_mm[0] < 15.0, "guided should land on the wall: {guided:?}");
    let l = guided.localization.unwrap();
    assert!(!l.hit && l.dice == 0.0 && l.centroid_distance_mm > 20.0, "{l:?}");
    let paper = SelectParams { localize: Localize::None, sizing: Sizing::Candidates, ..SelectParams::default() };
    let line = verdict(Rule::Guided, Some(&guided), true, true, &paper);
    assert!(line.starts_with("MISS") && line.contains("Dice 0.00"), "{line}");
    // The oracle still finds the nodule among the candidates (Dice of a 22 mm blob against a
    // 14 mm truth: 2·7³/(11³ + 7³) ≈ 0.41).
    let oracle = analysis.oracle().unwrap();
    assert!(oracle.any_hit && (oracle.best_dice - 0.41).abs() < 0.1, "{oracle:?}");
    // The blind persistence rule sets the face-touching wall aside and finds the nodule.
    let blind = analysis.describe(Rule::BlindPersistent, analysis.persistent(None).unwrap());
    assert!(blind.localization.unwrap().hit, "{blind:?}");
    let expected_d = equivalent_diameter_mm(4.0 / 3.0 * std::f64::consts::PI * 11f64.powi(3));
    assert!((blind.candidate.diameter_mm - expected_d).abs() < 3.0, "{blind:?}");
}

/// A chest cut by the box, on a 64 × 48 × 40 grid of 3 mm cells: mediastinum (0.7) for
/// x < 3, chest wall (0.7) for 35 ≤ y < 38 with air (0) beyond it — both touch the box faces,
/// as the lungs (0.12, with a ripple) do — a 10.5 mm radius nodule (0.7) in the lung, and a
/// 7 mm radius decoy (0.7) in the air outside the chest, of the annotated diameter.
fn chest() -> (Volume<f32>, [usize; 3]) {
    let g = Geometry { dims: [64, 48, 40], ..geometry([1; 3], 3.0, 0.0) };
    let nodule = [40usize, 20, 20];
    let mut data = vec![0f32; g.len()];
    for z in 0..40 {
        for y in 0..48 {
            for x in 0..64 {
                let d = |c: [usize; 3]| {
                    let sq = |a: usize, b: usize| (a as f64 - b as f64).powi(2);
                    3.0 * (sq(x, c[0]) + sq(y, c[1]) + sq(z, c[2])).sqrt()
                };
                let ripple = 0.03 * ((x as f32 * 0.9).sin() * (y as f32 * 1.3).cos() * (z as f32 * 0.7).sin());
                data[x + 64 * (y + 48 * z)] =
                    if x < 3 || (35..38).contains(&y) || d(nodule) <= 10.5 || d([55, 44, 33]) <= 7.0 {
                        0.7
                    } else if y >= 38 {
                        0.0
                    } else {
                        0.12 + ripple
                    };
            }
        }
    }
    (Volume { geometry: g, data }, nodule)
}

#[test]
fn the_lung_field_and_the_blob_centre_are_found_in_the_density_itself() {
    use aret_pipe::kernels::filters::distance_inside_mm;
    use aret_pipe::kernels::lung_mask::{blob_sites, lung_field, ranked_blobs};
    let (density, nodule) = chest();
    let (dims, spacing) = (density.geometry.dims, density.geometry.spacing_mm);
    let at = |v: [usize; 3]| v[0] + dims[0] * (v[1] + dims[1] * v[2]);
    let lungs = lung_field(&density.data, dims, spacing).expect("a lung field");
    assert!(lungs.field[at(nodule)], "the nodule lies in the (hole-filled) lung field");
    assert!(!lungs.field[at([1, 20, 20])], "mediastinum is not lung");
    assert!(!lungs.field[at([40, 42, 20])] && !lungs.field[at([55, 44, 33])], "outside air is not lung");
    assert!(lungs.field[at([50, 10, 5])], "parenchyma touching the box faces is lung");
    let sites = blob_sites(&distance_inside_mm(&lungs.field, dims, spacing), dims, spacing, 8.0);
    let ranked = ranked_blobs(&density.data, dims, spacing, &[6.0, 9.0, 13.0], &sites);
    let found = *ranked.first().expect("a blob");
    let off: usize = (0..3).map(|a| found.voxel[a].abs_diff(nodule[a])).sum();
    assert!(off <= 1, "the blob centre {found:?} is the nodule's {nodule:?}");
    // The paper's guided rule takes the decoy (it touches nothing of the nodule); sized
    // through the centre it takes the nodule.
    let levels = levels(&density, &paper_sweep()).unwrap();
    let analysis = Analysis::new(&levels, None, &density.geometry);
    let holds_nodule = |sel: (usize, u32)| levels[sel.0].components.labels[at(nodule)] == sel.1;
    let anywhere = analysis.choose(Rule::Guided, Some(14.0), None).unwrap();
    assert!(!holds_nodule(anywhere), "the unlocalised guided rule should be fooled by the decoy");
    let through = analysis.choose(Rule::Guided, Some(14.0), Some(at(found.voxel))).unwrap();
    assert!(holds_nodule(through));
    let blind = analysis.persistent(Some(at(found.voxel))).unwrap();
    assert!(holds_nodule(blind));
}

#[test]
fn blob_sites_keep_away_from_the_region_edges_and_the_lattice_faces() {
    use aret_pipe::kernels::filters::distance_inside_mm;
    use aret_pipe::kernels::lung_mask::blob_sites;
    // A region that fills the lattice but for one unset node: only the faces and that node bound it.
    let (dims, spacing) = ([20, 16, 12], [1.0, 1.5, 2.0]);
    let at = |x: usize, y: usize, z: usize| x + dims[0] * (y + dims[1] * z);
    let mut region = vec![true; dims.iter().product()];
    region[at(14, 8, 6)] = false;
    let sites = blob_sites(&distance_inside_mm(&region, dims, spacing), dims, spacing, 3.0);
    // To a face: (i + 1) nodes before it, (n − i) after it, times the spacing; > 3 mm.
    let away = |i: usize, n: usize, s: f64| ((i + 1).min(n - i) as f64) * s > 3.0;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let from_hole = (((x as f64 - 14.0) * spacing[0]).powi(2)
                    + ((y as f64 - 8.0) * spacing[1]).powi(2)
                    + ((z as f64 - 6.0) * spacing[2]).powi(2))
                .sqrt();
                let expected = away(x, dims[0], spacing[0])
                    && away(y, dims[1], spacing[1])
                    && away(z, dims[2], spacing[2])
                    && from_hole > 3.0;
                assert_eq!(sites[at(x, y, z)], expected, "node ({x}, {y}, {z})");
            }
        }
    }
    assert!(sites[at(5, 8, 6)] && !sites[at(2, 8, 6)] && !sites[at(5, 8, 0)] && !sites[at(16, 8, 6)]);
}

/// Two balls of radius 9 mm on 2 mm cells, 40 mm apart in uniform parenchyma (0.1): the
/// brighter (0.8) at the first centre, the fainter (`weak_level`) at the second.
fn two_balls(weak_level: f32) -> (Volume<f32>, [usize; 3], [usize; 3]) {
    let g = Geometry { dims: [48, 40, 36], ..geometry([1; 3], 2.0, 0.0) };
    let (strong, weak) = ([14usize, 20, 18], [34usize, 20, 18]);
    let mut data = vec![0.1f32; g.len()];
    for (i, v) in data.iter_mut().enumerate() {
        let p = [i % 48, (i / 48) % 40, i / (48 * 40)];
        let dist_mm = |c: [usize; 3]| 2.0 * (0..3).map(|a| (p[a] as f64 - c[a] as f64).powi(2)).sum::<f64>().sqrt();
        if dist_mm(strong) <= 9.0 {
            *v = 0.8;
        } else if dist_mm(weak) <= 9.0 {
            *v = weak_level;
        }
    }
    (Volume { geometry: g, data }, strong, weak)
}

#[test]
fn blob_searches_rank_every_peak_and_take_the_strongest_they_accept() {
    use aret_pipe::kernels::filters::hessian_blob_response;
    use aret_pipe::kernels::lung_mask::ranked_blobs;
    let (density, strong, weak) = two_balls(0.5);
    let g = density.geometry.clone();
    let (dims, spacing) = (g.dims, g.spacing_mm);
    let sites = vec![true; g.len()];
    let ranked = ranked_blobs(&density.data, dims, spacing, &[5.0], &sites);
    assert!(ranked.windows(2).all(|w| w[0].response >= w[1].response), "strongest first");
    let response = hessian_blob_response(&density.data, dims, spacing, 5.0);
    assert_eq!(ranked[0].response, response.iter().copied().fold(f32::MIN, f32::max), "the first is the maximum");
    let off = |v: [usize; 3], c: [usize; 3]| (0..3).map(|a| v[a].abs_diff(c[a])).max().unwrap();
    assert!(off(ranked[0].voxel, strong) <= 1, "{:?}", ranked[0]);
    assert!(off(ranked[1].voxel, weak) <= 1, "{:?}", ranked[1]);
    // The guided search (18 mm annotated: scale 5.2 mm) takes the strongest blob it accepts.
    let params = blob_search(strongest());
    let find = |accept: &(dyn Fn(Search, &aret_pipe::stage::select::Centre) -> bool + Sync)| {
        centres_in(&params, &density, &|s, c| accept(s, c).into())
    };
    let all = find(&|_, _| true);
    let first = all.guided.expect("a guided centre");
    assert_eq!((first.rank, off(first.voxel, strong) <= 1), (0, true));
    let not_strong = |_: Search, c: &aret_pipe::stage::select::Centre| off(c.voxel, strong) > 2;
    let passed_over = find(&not_strong);
    let second = passed_over.guided.expect("the weaker ball");
    assert!(second.rank >= 1 && off(second.voxel, weak) <= 1, "{second:?}");
    assert!(find(&|_, _| false).note.expect("a note").contains("could be sized"));
    // The guided search answers at the scale matched to the annotated diameter: d / (2√3).
    let matched_mm = 18.0 / (2.0 * 3f64.sqrt());
    assert!((first.blob.expect("a blob").scale_mm - matched_mm).abs() < 1e-9, "{first:?}");
}

#[test]
fn a_rival_blob_that_answers_nearly_as_strongly_makes_the_centre_ambiguous() {
    let off = |v: [f64; 3], c: [usize; 3]| (0..3).map(|a| (v[a] / 2.0 - c[a] as f64).abs()).fold(0.0, f64::max);
    let search = |weak_level: f32, rival_ratio: f64, accept: &(dyn Fn(Search, &Centre) -> bool + Sync)| {
        let (density, strong, weak) = two_balls(weak_level);
        let params = blob_search(BlobParams { rival_ratio, ..strongest() });
        let found = centres_in(&params, &density, &|s, c| accept(s, c).into());
        let taken = found.guided.expect("a guided centre");
        assert!(off(taken.position_mm, strong) <= 1.0, "{taken:?}");
        (taken, weak)
    };
    // The fainter ball is the runner-up, 40 mm away: the strong ball's own off-centre peaks,
    // within √3 × its scale, are not rivals. Its response ratio is the balls' contrast ratio.
    for (weak_level, expected_ratio) in [(0.5f32, 0.4 / 0.7), (0.75, 0.65 / 0.7)] {
        let (taken, weak) = search(weak_level, 0.7, &|_, _| true);
        let rival = taken.runner_up.clone().expect("a runner-up");
        assert!(off(rival.position_mm, weak) <= 1.0 && (rival.distance_mm - 40.0).abs() <= 2.0, "{rival:?}");
        assert!((rival.ratio - expected_ratio).abs() < 0.05, "{rival:?} against {expected_ratio}");
        assert_eq!(taken.ambiguous, expected_ratio >= 0.7, "{taken:?}");
    }
    // The rival must be one the search would accept; and `rival_ratio` sets the line.
    let (taken, _) = search(0.75, 0.7, &|_, c| c.position_mm[0] < 50.0);
    assert!(taken.runner_up.as_ref().is_none_or(|r| r.position_mm[0] < 50.0) && !taken.ambiguous, "{taken:?}");
    let (taken, _) = search(0.5, 0.5, &|_, _| true);
    assert!(taken.ambiguous, "{taken:?}");
}

#[test]
fn the_roundness_tie_break_takes_the_roundest_of_the_blobs_that_answer_alike() {
    use aret_pipe::stage::select::{RegionShape, TieBreak};
    let near = |v: [f64; 3], c: [usize; 3]| (0..3).all(|a| (v[a] / 2.0 - c[a] as f64).abs() <= 1.0);
    // The caller measures the strong ball's region as drawn out (0.3) and the weak one's as
    // round (0.9); the search decides only from what it is told.
    let taken = |weak_level: f32, tie_break: TieBreak| {
        let (density, strong, weak) = two_balls(weak_level);
        let params = blob_search(BlobParams { tie_break, ..strongest() });
        let judge = |_: Search, c: &Centre| Weighed::Accepted {
            region: Some(RegionShape {
                roundness: if near(c.position_mm, strong) { 0.3 } else { 0.9 },
                diameter_mm: 12.0,
                peak_score: 1.0,
            }),
        };
        let found = centres_in(&params, &density, &judge);
        let taken = found.guided.expect("a guided centre");
        (near(taken.position_mm, strong), near(taken.position_mm, weak), taken)
    };
    // At 0.65 / 0.7 of the strong ball's response the weak one contends, and is rounder.
    let (on_strong, on_weak, centre) = taken(0.75, TieBreak::Roundness);
    assert!(on_weak && !on_strong && centre.roundness() == Some(0.9), "{centre:?}");
    // Its runner-up is then the stronger ball, with a ratio above 1: still ambiguous.
    let rival = centre.runner_up.clone().expect("the strong ball");
    assert!(rival.ratio > 1.0 && rival.roundness == Some(0.3) && centre.ambiguous, "{centre:?}");
    // The strongest response wins by default, and a blob below the line does not contend.
    assert!(taken(0.75, TieBreak::Response).0);
    assert!(taken(0.5, TieBreak::Roundness).0);
}

#[test]
fn the_learned_tie_break_takes_the_blob_the_built_in_ranking_scores_highest() {
    use aret_pipe::stage::select::{BlobRanker, RegionShape};
    let near = |v: [f64; 3], c: [usize; 3]| (0..3).all(|a| (v[a] / 2.0 - c[a] as f64).abs() <= 1.0);
    let (density, strong, weak) = two_balls(0.5);
    // A nodule-like region (round, 20 mm, faint peak) and a vessel-like one (drawn out, 60 mm,
    // a dense peak), given to one ball and then the other.
    let nodule_like = RegionShape { roundness: 0.9, diameter_mm: 20.0, peak_score: 0.2 };
    let vessel_like = RegionShape { roundness: 0.1, diameter_mm: 60.0, peak_score: 1.0 };
    let params = blob_search(BlobParams { blind_tie_break: TieBreak::Learned, ..strongest() });
    let ranker = BlobRanker::built_in();
    let blind_on_weak = |weak_is_nodule_like: bool| {
        let judge = |_: Search, c: &Centre| {
            let on_weak = near(c.position_mm, weak);
            let region = if on_weak == weak_is_nodule_like { nodule_like } else { vessel_like };
            Weighed::Accepted { region: Some(region) }
        };
        let found = centres_in(&params, &density, &judge);
        let blind = found.blind.expect("a blind centre");
        // Every accepted blob is recorded, strongest first, the taken one among them.
        let ranks: Vec<usize> = found.blind_accepted.iter().map(|c| c.rank).collect();
        assert!(ranks.windows(2).all(|w| w[0] < w[1]) && ranks.contains(&blind.rank), "{ranks:?}");
        // Every accepted blob carries the ranking's score, and the taken one has the highest.
        let strongest = found.blind_accepted.iter().map(|c| c.blob.unwrap().response).fold(0.0, f32::max);
        for c in &found.blind_accepted {
            assert_eq!(c.ranking_score, ranker.score(c, strongest), "{c:?}");
        }
        let best = found.blind_accepted.iter().filter_map(|c| c.ranking_score).fold(f64::MIN, f64::max);
        assert_eq!(blind.ranking_score, Some(best), "{blind:?}");
        // The guided search (tie_break "response") keeps the strongest blob.
        assert!(near(found.guided.expect("a guided centre").position_mm, strong));
        near(blind.position_mm, weak)
    };
    // The ranking follows the regions, not the response alone: the nodule-like ball is taken.
    assert!(blind_on_weak(true) && !blind_on_weak(false));
}

#[test]
fn the_learned_ranking_is_the_blind_searchs_only_and_its_weights_key_the_stage() {
    let learned = BlobParams { blind_tie_break: TieBreak::Learned, ..BlobParams::default() };
    assert!(blob_search(learned.clone()).check().is_ok());
    assert!(blob_search(learned.clone()).key()["blob_ranker"]["weights"].is_array());
    assert!(blob_search(BlobParams { blind_tie_break: TieBreak::Roundness, ..learned.clone() })
        .key()
        .get("blob_ranker")
        .is_none());
    let e = blob_search(BlobParams { tie_break: TieBreak::Learned, ..learned }).check().unwrap_err().to_string();
    assert!(e.contains("tie_break = \"learned\"") && e.contains("blind_tie_break"), "{e}");
}

#[test]
fn with_no_guided_centre_the_guided_rule_may_fall_back_to_the_blind_one() {
    let (density, strong, _) = two_balls(0.3);
    let params = blob_search(strongest());
    let near = |v: [f64; 3], c: [usize; 3]| (0..3).all(|a| (v[a] / 2.0 - c[a] as f64).abs() <= 1.0);
    // The guided search accepts nothing; the blind one takes the strong ball.
    let found = centres_in(&params, &density, &|s, _| Weighed::from(s == Search::Blind));
    assert!(found.guided.is_none());
    let blind = found.blind.clone().expect("a blind centre");
    assert!(near(blind.position_mm, strong) && !blind.from_blind);
    // The guided size check rejects the blind centre too: still no guided centre.
    let mut rejected = found.clone();
    rejected.fall_back_to_blind(0.0, |_: &Centre| Weighed::PassedOver);
    assert!(rejected.guided.is_none());
    // It passes: the guided rule sizes from the blind centre, and says so.
    let mut taken = found.clone();
    taken.fall_back_to_blind(0.0, |_: &Centre| Weighed::from(true));
    let guided = taken.guided.clone().expect("the blind centre");
    assert!(guided.from_blind && guided.voxel == blind.voxel, "{guided:?}");
    // A guided centre of its own is never replaced.
    let mut own = taken.clone();
    own.blind = Some(Centre { voxel: [0, 0, 0], ..blind });
    own.fall_back_to_blind(0.0, |_: &Centre| Weighed::from(true));
    assert_eq!(own.guided, taken.guided);
}

#[test]
fn a_guided_centre_far_fainter_than_the_blind_one_gives_way_to_it() {
    use aret_pipe::stage::select::RegionShape;
    let (density, strong, weak) = two_balls(0.3);
    let params = blob_search(strongest());
    let found = centres_in(&params, &density, &|_, _| Weighed::from(true));
    let shape = |peak_score| Some(RegionShape { roundness: 0.8, diameter_mm: 18.0, peak_score });
    let blind = Centre { voxel: strong, region: shape(0.30), ..found.blind.clone().expect("a blind centre") };
    let guided = Centre { voxel: weak, region: shape(0.05), ..found.guided.clone().expect("a guided centre") };
    let with = |guided: Centre| aret_pipe::stage::select::Centres {
        guided: Some(guided),
        blind: Some(blind.clone()),
        ..found.clone()
    };
    // 0.05 against 0.30: under a ratio of 0.5 the blind centre is taken, and the peak it
    // replaced is recorded; under 0.1 and 0 (off) the guided centre stays.
    let mut replaced = with(guided.clone());
    replaced.fall_back_to_blind(0.5, |_: &Centre| Weighed::from(true));
    let taken = replaced.guided.expect("a centre");
    assert!(taken.from_blind && taken.voxel == strong && taken.replaced_guided_peak == Some(0.05), "{taken:?}");
    for ratio in [0.0, 0.1] {
        let mut kept = with(guided.clone());
        kept.fall_back_to_blind(ratio, |_: &Centre| Weighed::from(true));
        assert_eq!(kept.guided.as_ref(), Some(&guided), "ratio {ratio}");
    }
    // Not if the blind centre fails the guided size check, nor without regions to compare.
    let mut rejected = with(guided.clone());
    rejected.fall_back_to_blind(0.5, |_: &Centre| Weighed::PassedOver);
    assert_eq!(rejected.guided.as_ref(), Some(&guided));
    let mut unmeasured = with(Centre { region: None, ..guided.clone() });
    unmeasured.fall_back_to_blind(0.5, |_: &Centre| Weighed::from(true));
    assert!(!unmeasured.guided.expect("a centre").from_blind);
}
