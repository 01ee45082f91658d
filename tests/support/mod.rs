pub mod chest;
pub mod cohort;
pub mod dicom_writer;
