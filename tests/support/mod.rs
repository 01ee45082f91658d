pub mod chest;
pub mod cohort;
pub mod dicom_writer;
pub mod leases;
pub mod toy_stages;
