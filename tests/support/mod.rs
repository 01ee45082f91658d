pub mod chest;
pub mod dicom_writer;
