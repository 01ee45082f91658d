pub mod dicom_writer;
