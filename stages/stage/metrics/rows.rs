//! One row per patient of `results.csv` (SPEC §4, columns in order), from its `result.json`
//! and training log.

use crate::stage::select::{SelectResult, Selection};
use serde::Serialize;

/// SPEC §3 metrics: S < 10 mm ≤ M ≤ 20 mm < L, by the annotated diameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SizeClass {
    Small,
    Medium,
    Large,
}

impl SizeClass {
    pub fn of(diameter_mm: f64) -> SizeClass {
        if diameter_mm < 10.0 {
            SizeClass::Small
        } else if diameter_mm <= 20.0 {
            SizeClass::Medium
        } else {
            SizeClass::Large
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            SizeClass::Small => "small",
            SizeClass::Medium => "medium",
            SizeClass::Large => "large",
        }
    }
}

/// How solid the nodule is, by its readers' mean LIDC texture rating (1 ground glass … 5 solid):
/// `solid` from [`Texture::SOLID_RATING`] up (ratings 4 and 5, soft tissue: the phantom draws
/// them at −50 and +30 HU), `subsolid` below (part-solid 3, non-solid 1 and 2: −250 to −650 HU).
/// Fleischner's split: a subsolid nodule stands far less above the lung than a solid one, and
/// radiographs miss it most. Reported beside the size classes, never used by a rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Texture {
    Solid,
    Subsolid,
}

impl Texture {
    /// The mean rating from which a nodule counts as solid.
    pub const SOLID_RATING: f64 = 3.5;

    /// The class of a mean rating; `None` where there is none (no rated read).
    pub fn of(texture_mean: f64) -> Option<Texture> {
        texture_mean.is_finite().then_some(if texture_mean >= Texture::SOLID_RATING {
            Texture::Solid
        } else {
            Texture::Subsolid
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Texture::Solid => "solid",
            Texture::Subsolid => "subsolid",
        }
    }
}

/// Where the nodule lies: enclosed by the lung, or against its wall (some of its consensus
/// outside the CT's filled lung field: `ingest/target_site.json`). Three views show a nodule
/// fused with the chest wall or the mediastinum worst. Reported beside size and texture, never
/// used by a rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Site {
    Enclosed,
    Attached,
}

impl Site {
    pub fn of(attached: bool) -> Site {
        if attached {
            Site::Attached
        } else {
            Site::Enclosed
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Site::Enclosed => "enclosed",
            Site::Attached => "attached",
        }
    }
}

/// A selection's volume and localization, as the table reports it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Measured {
    pub volume_mm3: f64,
    pub ape_pct: f64,
    pub hit: bool,
    pub dice: f64,
    pub centroid_dist_mm: f64,
    /// Whether the rule's centre had a rival answering nearly as strongly (select's
    /// `ambiguous`); `None` where the rule sized no blob centre.
    pub ambiguous: Option<bool>,
}

/// One patient with a ground-truth target.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PatientRow {
    pub patient: String,
    pub size_class: SizeClass,
    /// The target's texture class; `None` where its readers gave no rating.
    pub texture: Option<Texture>,
    /// Whether the target lies against the lung's wall; `None` where ingest could not tell.
    pub site: Option<Site>,
    pub gt_volume_mm3: f64,
    pub gt_diameter_mm: f64,
    /// The primary (guided by default) selection; `None` when no candidate survived.
    pub ours: Option<Measured>,
    pub mesh_volume_mm3: Option<f64>,
    pub percentile: Option<f64>,
    pub blind: Option<Measured>,
    pub sphere_volume_mm3: f64,
    pub sphere_ape_pct: f64,
    /// The median over the target's readers of each one's APE against their consensus; `None`
    /// with fewer than two readers (one reader's consensus is that reader's own contour).
    pub reader_ape_pct: Option<f64>,
    pub oracle_hit: bool,
    /// Whether the guided and the blind rules' centres (`localize`) lie on the nodule: `None`
    /// where the rule found none. A hit through a centre elsewhere is a large candidate that
    /// grazes the nodule, not localization.
    pub centre_on_nodule: CentreOnNodule,
}

/// Whether each rule's centre lies on the nodule (select's diagnostic `on_nodule`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct CentreOnNodule {
    pub guided: Option<bool>,
    pub blind: Option<bool>,
}

/// Absolute percentage error of `predicted` against `truth`.
pub fn ape_pct(predicted: f64, truth: f64) -> f64 {
    (predicted - truth).abs() / truth * 100.0
}

/// The median APE of `reader_volumes_mm3` against their consensus `gt`, with two readers or more.
pub fn reader_ape_pct(reader_volumes_mm3: &[f64], gt: f64) -> Option<f64> {
    let apes: Vec<f64> = reader_volumes_mm3.iter().map(|&v| ape_pct(v, gt)).collect();
    (apes.len() >= 2).then(|| crate::kernels::stats::median(&apes))
}

impl PatientRow {
    /// The row of `result`, or `None` when the patient has no ground-truth target. `texture_mean`
    /// is the target's mean texture rating (`ground_truth.json`), `site` where it lies
    /// (`target_site.json`).
    pub fn new(result: &SelectResult, texture_mean: Option<f64>, site: Option<Site>) -> Option<PatientRow> {
        let (gt, d) = (result.gt_volume_mm3?, result.annotated_diameter_mm?);
        let measured = |s: &Selection| {
            let l = s.localization.expect("a patient with a target has localization");
            let centre = result.centres.of(s.rule);
            Measured {
                volume_mm3: s.candidate.volume_mm3,
                ape_pct: ape_pct(s.candidate.volume_mm3, gt),
                hit: l.hit,
                dice: l.dice,
                centroid_dist_mm: l.centroid_distance_mm,
                ambiguous: centre.filter(|c| c.blob.is_some()).map(|c| c.ambiguous),
            }
        };
        let sphere = std::f64::consts::PI / 6.0 * d.powi(3);
        let primary = result.selection(result.primary);
        Some(PatientRow {
            patient: result.patient.clone(),
            size_class: SizeClass::of(d),
            texture: texture_mean.and_then(Texture::of),
            site,
            gt_volume_mm3: gt,
            gt_diameter_mm: d,
            ours: primary.map(measured),
            mesh_volume_mm3: result.mesh_volume_mm3,
            percentile: primary.map(|s| s.candidate.percentile),
            blind: result.selection(result.blind_rule).map(measured),
            sphere_volume_mm3: sphere,
            sphere_ape_pct: ape_pct(sphere, gt),
            reader_ape_pct: reader_ape_pct(&result.reader_volumes_mm3, gt),
            oracle_hit: result.oracle.as_ref().is_some_and(|o| o.any_hit),
            centre_on_nodule: CentreOnNodule {
                guided: result.centres.guided.as_ref().and_then(|c| c.on_nodule),
                blind: result.centres.blind.as_ref().and_then(|c| c.on_nodule),
            },
        })
    }
}

pub const RESULTS_HEADER: &str = "patient,size_class,gt_volume_mm3,gt_diameter_mm,pred_volume_mm3,ape_pct,\
hit,dice,centroid_dist_mm,mesh_volume_mm3,percentile,blind_volume_mm3,blind_ape_pct,blind_hit,blind_dice,\
sphere_volume_mm3,sphere_ape_pct,oracle_hit";

/// `results.csv`: the SPEC's columns in order; an empty field where there is no value (no
/// candidate survived), a non-finite distance as empty too. Fields are quoted where they must be
/// (RFC 4180), and a patient ID that a spreadsheet would run as a formula is written as text
/// ([`spreadsheet_text`]).
pub fn results_csv(rows: &[PatientRow]) -> String {
    let num = |v: Option<f64>| v.filter(|v| v.is_finite()).map(|v| format!("{v:.4}")).unwrap_or_default();
    let flag = |v: Option<bool>| v.map(|b| u8::from(b).to_string()).unwrap_or_default();
    let mut csv = csv::WriterBuilder::new().terminator(csv::Terminator::Any(b'\n')).from_writer(Vec::new());
    let header: Vec<&str> = RESULTS_HEADER.split(',').collect();
    csv.write_record(&header).expect("writes to memory");
    for r in rows {
        let (o, b) = (r.ours.as_ref(), r.blind.as_ref());
        csv.write_record([
            spreadsheet_text(&r.patient),
            r.size_class.name().to_string(),
            num(Some(r.gt_volume_mm3)),
            num(Some(r.gt_diameter_mm)),
            num(o.map(|m| m.volume_mm3)),
            num(o.map(|m| m.ape_pct)),
            flag(o.map(|m| m.hit)),
            num(o.map(|m| m.dice)),
            num(o.map(|m| m.centroid_dist_mm)),
            num(r.mesh_volume_mm3),
            num(r.percentile),
            num(b.map(|m| m.volume_mm3)),
            num(b.map(|m| m.ape_pct)),
            flag(b.map(|m| m.hit)),
            num(b.map(|m| m.dice)),
            num(Some(r.sphere_volume_mm3)),
            num(Some(r.sphere_ape_pct)),
            flag(Some(r.oracle_hit)),
        ])
        .expect("writes to memory");
    }
    String::from_utf8(csv.into_inner().expect("writes to memory")).expect("the fields are UTF-8")
}

/// `text` as a spreadsheet shows it rather than runs it: a leading `=`, `+`, `-`, `@`, tab or
/// carriage return starts a formula in Excel, LibreOffice and Google Sheets, so such text gets
/// a leading apostrophe (OWASP's advice on CSV injection).
pub fn spreadsheet_text(text: &str) -> String {
    match text.chars().next() {
        Some('=' | '+' | '-' | '@' | '\t' | '\r') => format!("'{text}"),
        _ => text.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_readers_error_is_their_median_and_needs_two_of_them() {
        assert_eq!(reader_ape_pct(&[], 100.0), None);
        assert_eq!(reader_ape_pct(&[150.0], 100.0), None, "one reader's consensus is that reader's contour");
        assert_eq!(reader_ape_pct(&[90.0, 130.0], 100.0), Some(20.0));
        assert_eq!(reader_ape_pct(&[100.0, 80.0, 150.0, 60.0], 100.0), Some(30.0));
    }

    #[test]
    fn size_classes_follow_the_spec() {
        assert_eq!(SizeClass::of(9.99), SizeClass::Small);
        assert_eq!(SizeClass::of(10.0), SizeClass::Medium);
        assert_eq!(SizeClass::of(20.0), SizeClass::Medium);
        assert_eq!(SizeClass::of(20.01), SizeClass::Large);
    }

    #[test]
    fn ratings_4_and_5_are_solid_3_and_below_subsolid() {
        assert_eq!(Texture::of(5.0), Some(Texture::Solid));
        assert_eq!(Texture::of(3.5), Some(Texture::Solid), "readers split between 3 and 4");
        assert_eq!(Texture::of(3.25), Some(Texture::Subsolid));
        assert_eq!(Texture::of(1.5), Some(Texture::Subsolid));
        assert_eq!(Texture::of(f64::NAN), None, "no rated read");
    }

    #[test]
    fn an_id_with_a_comma_quote_or_newline_stays_one_field_of_one_row() {
        let row = |patient: &str| PatientRow {
            patient: patient.to_string(),
            size_class: SizeClass::Medium,
            texture: None,
            site: None,
            gt_volume_mm3: 1000.0,
            gt_diameter_mm: 12.0,
            ours: None,
            mesh_volume_mm3: None,
            percentile: None,
            blind: None,
            sphere_volume_mm3: 900.0,
            sphere_ape_pct: 10.0,
            reader_ape_pct: None,
            oracle_hit: false,
            centre_on_nodule: CentreOnNodule::default(),
        };
        let ids = ["a,b", "say \"hi\"", "two\nlines", "=HYPERLINK(\"http://x\")", "LIDC-IDRI-0001"];
        let text = results_csv(&ids.map(row));
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let read: Vec<csv::StringRecord> = reader.records().map(Result::unwrap).collect();
        assert_eq!(read.len(), ids.len());
        for (record, id) in read.iter().zip(ids) {
            assert_eq!(record.len(), 18);
            assert_eq!(&record[0], spreadsheet_text(id));
            assert_eq!(&record[1], "medium");
            assert_eq!(&record[17], "0");
        }
    }

    #[test]
    fn text_a_spreadsheet_would_run_is_written_as_text() {
        for formula in ["=1+2", "+SUM(A1)", "-2+3", "@cmd", "\tx", "\rx"] {
            assert_eq!(spreadsheet_text(formula), format!("'{formula}"));
        }
        assert_eq!(spreadsheet_text("LIDC-IDRI-0001"), "LIDC-IDRI-0001");
        assert_eq!(spreadsheet_text(""), "");
    }

    #[test]
    fn the_header_has_the_specs_columns_but_the_wall_time() {
        assert_eq!(RESULTS_HEADER.split(',').count(), 18);
        assert!(RESULTS_HEADER.starts_with("patient,size_class,") && RESULTS_HEADER.ends_with(",oracle_hit"));
    }
}
