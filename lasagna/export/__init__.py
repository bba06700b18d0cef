"""lasagna.export"""
