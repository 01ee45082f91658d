pub mod chest;
pub mod cohort;
pub mod dicom_writer;
pub mod toy_stages;
