"""lasagna.document"""
